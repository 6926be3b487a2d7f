"""The live view: the swarms over the streets in sumo-gui, and a recorded video (``--gui``).

A GUI run drives sumo-gui through traci instead of libsumo (:class:`twin.sumo.session.SumoSession`
with ``gui`` set); the options and so the simulation are the same, and so are the results.
:class:`GuiDrawer` is called once per swarm step (``on_step`` of :func:`twin.patrol.run_patrol`)
while SUMO stands at that step's time, and draws on the network:

- the grid's cells as filled polygons under the roads, shaded by the importance the first shown
  swarm believes (the last ``T^k`` read in each cell's view, as ``belief_error`` scores it; 0
  before a first look) or by the true ``T^k`` (``--gui-shade``); obstacle cells grey;
- each shown swarm's drones as points of interest and their fields of view ``Adj(p)`` as
  outlines, one colour per swarm (:data:`SWARM_COLOURS`);
- active incidents as red squares.

With ``--record`` every step's view is saved (``traci.gui.screenshot``) and the frames are
assembled into an MP4 (imageio-ffmpeg) or a GIF (pillow). Without a display, :func:`display`
starts Xvfb on a free display number and stops it at the end. sumo-gui runs with its home in
twin's cache (:meth:`GuiSettings.home`), so the settings it saves on closing stay out of ``~``.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import tempfile
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from twin.errors import UserError

#: RGBA per shown swarm, in order (colour-blind-safe Okabe-Ito hues).
SWARM_COLOURS = [
    (0, 114, 178, 255),  # blue
    (213, 94, 0, 255),  # vermillion
    (0, 158, 115, 255),  # bluish green
    (204, 121, 167, 255),  # reddish purple
    (230, 159, 0, 255),  # orange
    (86, 180, 233, 255),  # sky blue
    (240, 228, 66, 255),  # yellow
    (0, 0, 0, 255),  # black
]
OBSTACLE_COLOUR = (120, 120, 120, 140)
INCIDENT_COLOUR = (220, 0, 0, 255)
SHADES = ("belief", "truth")
VIDEO_SUFFIXES = (".mp4", ".gif")
#: sumo-gui's view settings: vehicles exaggerated so that they show at city scale
GUI_SETTINGS = """<viewsettings>
    <scheme name="twin">
        <vehicles vehicleQuality="0" vehicle_minSize="3" vehicle_exaggeration="4"/>
    </scheme>
    <delay value="0"/>
</viewsettings>
"""
#: frames per second of a recorded video (one frame per swarm step)
FPS = 4


@dataclass
class GuiSettings:
    """What ``--gui`` shows and records."""

    swarms: Sequence[str] | None = None  # shown swarms, None: all
    shade: str = "belief"
    record: Path | None = None
    window: tuple[int, int] = (1280, 800)
    #: keep every step's screenshot here (``frame-00000.png`` ...), with or without ``record``
    frames_dir: Path | None = field(default=None, repr=False)

    def binary(self) -> str:
        import sumolib

        return sumolib.checkBinary("sumo-gui")

    def home(self) -> Path:
        """sumo-gui's home: ``sumo-gui/`` in twin's cache, where sumo-gui keeps the settings it
        saves on closing (its FOX registry ``.foxrc/``) instead of the user's home."""
        from twin.resources import CACHE_ENV, cache_dir

        home = cache_dir() / "sumo-gui"
        try:
            home.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise UserError(
                f"--gui: cannot create {home} for sumo-gui's settings ({exc.strerror}); "
                f"${CACHE_ENV} moves twin's cache"
            ) from None
        return home

    @contextlib.contextmanager
    def environment(self) -> Iterator[None]:
        """``HOME`` and ``XDG_CONFIG_HOME`` pointing into :meth:`home` while sumo-gui starts
        (it inherits them), restored afterwards."""
        home = self.home()
        values = {"HOME": str(home), "XDG_CONFIG_HOME": str(home / ".config")}
        saved = {name: os.environ.get(name) for name in values}
        os.environ.update(values)
        try:
            yield
        finally:
            for name, value in saved.items():
                if value is None:
                    os.environ.pop(name, None)
                else:
                    os.environ[name] = value

    def sumo_options(self) -> list[str]:
        """sumo-gui's options: start at once, close at the end, a fixed window size, vehicles
        drawn 4 times larger (seen at city scale); none of them changes the simulation."""
        w, h = self.window
        settings = self.home() / "twin-gui-settings.xml"
        if not settings.is_file() or settings.read_text() != GUI_SETTINGS:
            from twin.files import atomic_write

            atomic_write(settings, lambda p: p.write_text(GUI_SETTINGS))
        return [
            "--start", "--quit-on-end", "--window-size", f"{w},{h}", "--delay", "0",
            "--gui-settings-file", str(settings),
        ]  # fmt: skip


def check_settings(settings: GuiSettings, available: Sequence[str]) -> None:
    """Refuse bad ``--gui-*`` / ``--record`` values before anything runs (one line each)."""
    if settings.shade not in SHADES:
        raise UserError(f"--gui-shade {settings.shade}: choose from {', '.join(SHADES)}")
    for name in settings.swarms or ():
        if name not in available:
            raise UserError(
                f"--gui-swarms: {name!r} is not among the run's swarms; choose from "
                f"{', '.join(available)}"
            )
    if settings.record is not None:
        if settings.record.suffix.lower() not in VIDEO_SUFFIXES:
            raise UserError(f"--record {settings.record}: give a .mp4 or .gif file name")
        from twin.outputs import check_output_file

        if settings.record.exists() or settings.record.is_symlink():
            raise UserError(
                f"--record {settings.record}: the file exists, and --record never overwrites a "
                "file; remove it or give a new file name"
            )
        check_output_file(settings.record, "--record", need_mb=10)
        try:
            if settings.record.suffix.lower() == ".mp4":
                import imageio_ffmpeg  # noqa: F401
        except ImportError:
            raise UserError(
                f"--record {settings.record}: needs imageio-ffmpeg; pip install 'twin[gui]'"
            ) from None


@contextlib.contextmanager
def display(flag: str = "--gui") -> Iterator[str]:
    """A display for sumo-gui: ``$DISPLAY`` if set, else an Xvfb started here (stopped on exit)."""
    if os.environ.get("DISPLAY"):
        yield os.environ["DISPLAY"]
        return
    xvfb = shutil.which("Xvfb")
    if xvfb is None:
        raise UserError(
            f"{flag}: no display (DISPLAY is unset) and no Xvfb found; install it "
            "(apt-get install xvfb) or set DISPLAY"
        )
    read, write = os.pipe()
    proc = subprocess.Popen(
        [xvfb, "-displayfd", str(write), "-screen", "0", "1920x1200x24", "-nolisten", "tcp"],
        pass_fds=(write,),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    os.close(write)
    try:
        with os.fdopen(read) as fh:
            number = fh.readline().strip()  # Xvfb writes its display number once ready
        if not number:
            raise UserError(f"{flag}: Xvfb did not start; set DISPLAY to a running X server")
        os.environ["DISPLAY"] = f":{number}"
        try:
            yield os.environ["DISPLAY"]
        finally:
            os.environ.pop("DISPLAY", None)
    finally:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def importance_rgba(value: float) -> tuple[int, int, int, int]:
    """A cell's fill: transparent yellow at importance 0 to opaque red at 1 (on a square-root
    scale, which separates the low values most cells have)."""
    v = float(np.sqrt(np.clip(np.nan_to_num(value), 0.0, 1.0)))
    return (255, int(220 * (1 - v)), 0, int(25 + 175 * v))


def fov_outline(geometry, grid, i: int, j: int) -> list[tuple[float, float]]:
    """The outline of ``Adj(p)`` (the drone's cell and its 4 neighbours on the map): a plus."""
    c = geometry.cell_m
    left = geometry.x0 + j * c
    top = geometry.y_top - i * c
    up = c if i > 0 else 0.0
    down = c if i < grid.nx - 1 else 0.0
    west = c if j > 0 else 0.0
    east = c if j < grid.ny - 1 else 0.0
    x0, x1, y0, y1 = left, left + c, top - c, top
    return [
        (x0, y1 + up), (x1, y1 + up), (x1, y1), (x1 + east, y1), (x1 + east, y0), (x1, y0),
        (x1, y0 - down), (x0, y0 - down), (x0, y0), (x0 - west, y0), (x0 - west, y1), (x0, y1),
    ]  # fmt: skip


class GuiDrawer:
    """Draws every step of a run in sumo-gui (see the module docstring); one per command.

    :meth:`attach` binds it to a traffic source (a seed's SUMO run); calling it with
    ``(k, positions, importance)`` draws step ``k``; :meth:`finish` writes the video.
    """

    def __init__(self, settings: GuiSettings, swarms: Sequence[str]):
        self.settings = settings
        self.shown = list(settings.swarms) if settings.swarms else list(swarms)
        self.colours = {n: SWARM_COLOURS[s % len(SWARM_COLOURS)] for s, n in enumerate(swarms)}
        self.source = None
        self.frames: list[Path] = []
        self._tmp = None
        self._frames_dir = settings.frames_dir
        if settings.record is not None and self._frames_dir is None:
            self._tmp = tempfile.TemporaryDirectory(prefix="twin-frames-")
            self._frames_dir = Path(self._tmp.name)
        #: the view's ``((xmin, ymin), (xmax, ymax))`` in network metres (to place pixels)
        self.view_boundary = None
        self._fills: dict[str, tuple] = {}
        self._belief: np.ndarray | None = None
        self._ready = False

    def legend(self) -> str:
        names = {(0, 114, 178): "blue", (213, 94, 0): "vermillion", (0, 158, 115): "green",
                 (204, 121, 167): "purple", (230, 159, 0): "orange", (86, 180, 233): "sky blue",
                 (240, 228, 66): "yellow", (0, 0, 0): "black"}  # fmt: skip
        shown = ", ".join(f"{n} {names[self.colours[n][:3]]}" for n in self.shown)
        return f"gui: drones {shown}; cells shaded by {self.settings.shade}, obstacles grey"

    def attach(self, source) -> None:
        """Draw on ``source``'s SUMO run (its session starts with the GUI settings)."""
        source.gui = self.settings
        self.source = source
        self._ready = False

    def _traci(self):
        import traci

        return traci

    def _setup(self) -> None:
        traci, g, grid = self._traci(), self.source.geometry, self.source.grid
        c = g.cell_m
        for i in range(grid.nx):
            for j in range(grid.ny):
                x0, y1 = g.x0 + j * c, g.y_top - i * c
                shape = [(x0, y1), (x0 + c, y1), (x0 + c, y1 - c), (x0, y1 - c)]
                colour = OBSTACLE_COLOUR if grid.obstacles[i, j] else importance_rgba(0.0)
                traci.polygon.add(f"cell_{i}_{j}", shape, colour, fill=True, layer=-1)
        view = traci.gui.DEFAULT_VIEW
        traci.gui.setBoundary(view, g.x0, g.y_top - grid.nx * c, g.x0 + grid.ny * c, g.y_top)
        self.view_boundary = traci.gui.getBoundary(view)
        self._fills = {}
        self._belief = np.zeros(grid.shape)
        self._drones: set[str] = set()
        self._incidents: set[str] = set()
        self._ready = True

    def __call__(self, k: int, positions: Mapping[str, np.ndarray], importance: np.ndarray) -> None:
        if self.source is None:
            return
        if not self._ready:
            self._setup()
        traci, g, grid = self._traci(), self.source.geometry, self.source.grid
        self._shade(positions, importance)
        for name in self.shown:
            colour = self.colours[name]
            for d, (i, j) in enumerate(np.asarray(positions[name])):
                pid = f"{name}_{d}"
                x, y = g.cell_center(i, j)
                fov = fov_outline(g, grid, int(i), int(j))
                if pid not in self._drones:
                    size = 0.35 * g.cell_m
                    traci.poi.add(
                        pid, float(x), float(y), colour, layer=110, width=size, height=size
                    )
                    traci.polygon.add(
                        f"fov_{pid}", fov, colour, fill=False, layer=100, lineWidth=0.06 * g.cell_m
                    )
                    self._drones.add(pid)
                else:
                    traci.poi.setPosition(pid, float(x), float(y))
                    traci.polygon.setShape(f"fov_{pid}", fov)
        self._mark_incidents()
        if self._frames_dir is not None:
            frame = Path(self._frames_dir) / f"frame-{len(self.frames):05d}.png"
            traci.gui.screenshot(traci.gui.DEFAULT_VIEW, str(frame))
            self.frames.append(frame)
            self._pending = True
            if k == self.source.horizon:
                self.flush()

    def flush(self) -> None:
        """Take the last requested screenshot: sumo-gui takes it at the next simulation step,
        so advance SUMO by one step once every read is done (the results are unchanged)."""
        if getattr(self, "_pending", False):
            self._pending = False
            with contextlib.suppress(Exception):
                self._traci().simulationStep()

    def _shade(self, positions: Mapping[str, np.ndarray], importance: np.ndarray) -> None:
        grid = self.source.grid
        if self.settings.shade == "truth":
            truth = self.source.truth_map() if hasattr(self.source, "truth_map") else None
            values = np.asarray(importance if truth is None else truth)
        else:
            flat, valid = grid.view_index(np.asarray(positions[self.shown[0]]))
            belief = self._belief.ravel()
            belief[flat[valid]] = np.asarray(importance).ravel()[flat[valid]]
            values = self._belief
        traci = self._traci()
        levels = (
            np.round(np.sqrt(np.clip(np.nan_to_num(values), 0, 1)) * 20) ** 2 / 400
        )  # 21 shades
        for i, j in zip(*np.nonzero(grid.free), strict=True):
            colour = importance_rgba(levels[i, j])
            key = f"cell_{i}_{j}"
            if self._fills.get(key) != colour:
                traci.polygon.setColor(key, colour)
                self._fills[key] = colour

    def _mark_incidents(self) -> None:
        info = getattr(self.source, "incidents_info", None)
        if info is None:
            return
        traci, g = self._traci(), self.source.geometry
        now = float(traci.simulation.getTime())
        for n, rec in enumerate(info()):
            key = f"incident_{n}"
            applied, lifted = rec.get("applied_s"), rec.get("lifted_s")
            active = applied is not None and applied <= now and (lifted is None or lifted > now)
            if active and key not in self._incidents and "i" in rec and "j" in rec:
                x, y = g.cell_center(rec["i"], rec["j"])
                size = 0.25 * g.cell_m
                traci.poi.add(key, float(x), float(y), INCIDENT_COLOUR, layer=120, width=size,
                              height=size)  # fmt: skip
                self._incidents.add(key)
            elif not active and key in self._incidents:
                traci.poi.remove(key)
                self._incidents.discard(key)

    def finish(self) -> Path | None:
        """Assemble the recorded frames into ``--record``'s file; returns it (None: no record)."""
        if self.settings.record is None:
            return None
        try:
            frames = [f for f in self.frames if _wait_for(f)]
            if not frames:
                raise UserError(f"--record {self.settings.record}: no frame was recorded")
            write_video(self.settings.record, frames)
            return self.settings.record
        finally:
            if self._tmp is not None:
                self._tmp.cleanup()
                self._tmp = None


def _wait_for(path: Path, seconds: float = 5.0) -> bool:
    """Whether sumo-gui has written ``path`` (it does so asynchronously) within ``seconds``."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if path.exists() and path.stat().st_size > 0:
            return True
        time.sleep(0.05)
    return False


def write_video(path: Path, frames: Sequence[Path], fps: int = FPS) -> None:
    """The PNG ``frames`` as an MP4 (H.264 through imageio-ffmpeg's ffmpeg) or a GIF (pillow),
    written atomically."""
    from PIL import Image

    from twin.files import atomic_write

    images = [np.asarray(Image.open(f).convert("RGB")) for f in frames]
    h = min(im.shape[0] for im in images) // 2 * 2  # H.264 (yuv420p) needs even sizes
    w = min(im.shape[1] for im in images) // 2 * 2
    images = [np.ascontiguousarray(im[:h, :w]) for im in images]

    def write(tmp: Path) -> None:
        if path.suffix.lower() == ".gif":
            first, *rest = (Image.fromarray(im) for im in images)
            first.save(
                tmp, format="GIF", save_all=True, append_images=rest, duration=1000 // fps, loop=0
            )
            return
        import imageio_ffmpeg

        writer = imageio_ffmpeg.write_frames(
            str(tmp), (w, h), fps=fps, codec="libx264", macro_block_size=2,
            output_params=["-f", "mp4"], ffmpeg_log_level="error",
        )  # fmt: skip
        writer.send(None)
        for im in images:
            writer.send(im)
        writer.close()

    atomic_write(Path(path), write)
