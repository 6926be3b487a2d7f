"""Run reports: figures of the paper (Figs. 2-4, Table 2), the MFD and an animation, written
from a run folder's own files into ``RUN_DIR/report/`` as one self-contained HTML file, a
Markdown summary and the images."""

from twin.report.document import write_report
from twin.report.load import RunFiles, load_run

__all__ = ["RunFiles", "load_run", "write_report"]
