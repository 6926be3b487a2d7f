"""Run reports: figures of the paper (Figs. 2-4, Table 2), the MFD and an animation, written
from a run folder's own files into ``RUN_DIR/report/`` as one self-contained HTML file, a
Markdown summary and the images.

matplotlib keeps its font cache and config in twin's cache (``MPLCONFIGDIR``, unless the user
set it), so that drawing a report writes nothing into the user's home."""

import os

from twin.resources import cache_dir

os.environ.setdefault("MPLCONFIGDIR", str(cache_dir() / "matplotlib"))

from twin.report.document import write_report
from twin.report.load import RunFiles, load_run

__all__ = ["RunFiles", "load_run", "write_report"]
