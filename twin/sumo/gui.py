"""The live view: the swarms over the streets in sumo-gui, and a recorded video (``--gui``).

A GUI run drives sumo-gui through traci instead of libsumo (:class:`twin.sumo.session.SumoSession`
with ``gui`` set); the options and so the simulation are the same, and so are the results.
:class:`GuiDrawer` is called once per swarm step (``on_step`` of :func:`twin.patrol.run_patrol`)
while SUMO stands at that step's time, and draws on the network:

- the roads coloured by the lanes' speed over their limit (grey free flow, orange slow, dark red
  stopped) and the vehicles as dark triangles (:data:`GUI_SETTINGS`);
- the grid's cells as light filled polygons under the roads, shaded by the importance the first
  shown swarm believes (the last ``T^k`` read in each cell's view, as ``belief_error`` scores
  it; 0 before a first look) or by the true ``T^k`` (``--gui-shade``); obstacle cells grey;
- the shown swarms' drones (by default the learned and the best classical swarm,
  :func:`default_swarms`) as points of interest and their fields of view ``Adj(p)`` as
  outlines, one colour per swarm (:data:`SWARM_COLOURS`);
- active incidents as red squares;
- above the grid, a header: the clock (time of day and step ``k/T``), the legend (a square of
  each shown swarm's colour and its name) and what the cells and roads mean, written by
  sumo-gui as the types of points of interest, so in the window and in the frames alike.

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

#: RGBA per shown swarm, in order (colour-blind-safe Okabe-Ito hues; the first two stand apart
#: from the roads' grey-yellow-red speed colours).
SWARM_COLOURS = [
    (0, 114, 178, 255),  # blue
    (204, 121, 167, 255),  # reddish purple
    (0, 158, 115, 255),  # bluish green
    (0, 0, 0, 255),  # black
    (86, 180, 233, 255),  # sky blue
    (230, 159, 0, 255),  # orange
    (213, 94, 0, 255),  # vermillion
    (240, 228, 66, 255),  # yellow
]
#: the classical swarm shown by default, if in the run (else the first coordinated classical one)
BEST_CLASSICAL = "lookahead"
#: the learned swarm shown by default, if in the run (else the first learned one)
LEARNED = "rl"
OBSTACLE_COLOUR = (120, 120, 120, 140)
INCIDENT_COLOUR = (220, 0, 0, 255)
SHADES = ("belief", "truth")
VIDEO_SUFFIXES = (".mp4", ".gif")
#: the roads' colours by the lanes' mean speed over their speed limit ("by average relative
#: speed"): stopped dark red, slow orange, free flow grey (empty lanes count as free flow)
ROAD_SPEED_COLOURS = [
    (0.0, "160,0,0"),
    (0.3, "230,60,20"),
    (0.6, "250,170,0"),
    (0.85, "170,170,170"),
]
#: sumo-gui's road colouring: by relative speed for lanes (microscopic; its index,
#: ``laneEdgeMode``, and name as in SUMO 1.28), one grey for the edges of the mesoscopic model
#: (``--meso``): sumo-gui's mesoscopic speed colouring changes the simulation it draws (the
#: segments' mean speeds it reads are cached, so a replay drew another run than the recorded
#: one every few times), and a drawing must not change what it draws
ROAD_SPEED_SCHEMES = {
    False: (26, "by average relative speed "),
    True: (0, "uniform"),
}
#: sumo-gui's view settings: roads coloured by speed, lanes and vehicles (dark) widened to be seen
#: at the view's scale, the types of POIs written (the header's clock, legend and key)
GUI_SETTINGS = """<viewsettings>
    <scheme name="twin">
        <edges laneEdgeMode="{mode}" widthExaggeration="{lanes:g}" laneShowBorders="0"
               showLinkDecals="0" showLinkRules="0">
            <colorScheme name="{scheme}" interpolated="1">{entries}
            </colorScheme>
        </edges>
        <vehicles vehicleMode="1" vehicleQuality="0" showBlinker="0" vehicle_minSize="0"
                  vehicle_exaggeration="{vehicles:g}" vehicle_constantSize="0">
            <colorScheme name="uniform">
                <entry color="30,30,30"/>
            </colorScheme>
        </vehicles>
        <pois poiType_show="1" poiType_size="60" poiType_color="0,0,0"
              poiType_bgColor="255,255,255,0" poiType_constantSize="1"/>
    </scheme>
    <delay value="0"/>
</viewsettings>
"""


#: a lane's and a vehicle's size on screen, in pixels (at least their real size)
LANE_PX = 1.5
VEHICLE_PX = 5.0


def view_settings(mesoscopic: bool = False, metres_per_px: float | None = None) -> str:
    """:data:`GUI_SETTINGS` with the roads' colouring of the model (lanes by speed, or edges), and
    lanes (3.2 m) and vehicles (5 m) widened to :data:`LANE_PX` and :data:`VEHICLE_PX` at a
    view of ``metres_per_px`` (None: 8 m a pixel)."""
    mode, scheme = ROAD_SPEED_SCHEMES[mesoscopic]
    entries = "".join(
        f'\n                <entry color="{c}" threshold="{t:g}"/>' for t, c in ROAD_SPEED_COLOURS
    )
    if mesoscopic:  # one grey: its speed colouring changes the simulation (ROAD_SPEED_SCHEMES)
        entries = f'\n                <entry color="{ROAD_SPEED_COLOURS[-1][1]}"/>'

    scale = 8.0 if metres_per_px is None else metres_per_px
    return GUI_SETTINGS.format(
        mode=mode,
        scheme=scheme,
        entries=entries,
        lanes=max(1.0, round(LANE_PX * scale / 3.2, 1)),
        vehicles=max(1.0, round(VEHICLE_PX * scale / 5.0, 1)),
    )


#: frames per second of a recorded video (one frame per swarm step)
FPS = 4
#: the header above the grid (clock, legend, key): how far below a POI sumo-gui writes its type
#: and the height of a row, in pixels
TEXT_PX = 18
ROW_PX = 30
#: sumo-gui's window less its view (its menu, tool and status bars), in pixels (measured)
BARS_PX = (10, 186)
#: the POI whose type is the clock
CLOCK = "legend_clock"


@dataclass
class GuiSettings:
    """What ``--gui`` shows and records."""

    swarms: Sequence[str] | None = None  # shown swarms, None: :func:`default_swarms`
    shade: str = "belief"
    record: Path | None = None
    window: tuple[int, int] = (1280, 800)
    #: keep every step's screenshot here (``frame-00000.png`` ...), with or without ``record``
    frames_dir: Path | None = field(default=None, repr=False)
    #: the view's scale, set by :meth:`GuiDrawer.attach` (sizes lanes and vehicles)
    metres_per_px: float | None = field(default=None, repr=False)

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

    def sumo_options(self, mesoscopic: bool = False) -> list[str]:
        """sumo-gui's options: start at once, close at the end, a fixed window size, the view
        settings of :func:`view_settings`, twin its one TraCI client (a scenario's
        ``num-clients`` would keep it waiting for others), and a scenario's GUI options that
        would stop the run off: no breakpoints (pauses twin never lifts), no demo (a restart
        at the end) and no game; none of them changes the simulation."""
        w, h = self.window
        text = view_settings(mesoscopic, self.metres_per_px)
        settings = self.home() / f"twin-gui-settings{'-meso' if mesoscopic else ''}.xml"
        if not settings.is_file() or settings.read_text() != text:
            from twin.files import atomic_write

            atomic_write(settings, lambda p: p.write_text(text))
        return [
            "--start", "--quit-on-end", "--window-size", f"{w},{h}", "--delay", "0",
            "--gui-settings-file", str(settings), "--num-clients", "1", "--breakpoints", "",
            "--demo", "false", "--game", "false",
        ]  # fmt: skip


def default_swarms(swarms: Sequence[str]) -> list[str]:
    """The swarms drawn without ``--gui-swarms``, in the run's order: the learned swarm (``rl``,
    else the first learned one) and the best classical one (``lookahead``, else the first
    coordinated classical swarm: greedy-coordinated, visit-gain, tours; else the first
    non-learned one); the first swarm when neither is in the run. Known before any result."""
    from twin.planners import PLANNERS
    from twin.swarms import is_learned

    learned = [s for s in swarms if is_learned(s)]
    classical = [s for s in swarms if not is_learned(s)]
    coordinated = [s for s in classical if s in PLANNERS or s == "tours"]
    picks = {
        LEARNED if LEARNED in learned else next(iter(learned), None),
        BEST_CLASSICAL
        if BEST_CLASSICAL in classical
        else next(iter(coordinated + classical), None),
    }
    return [s for s in swarms if s in picks] or list(swarms[:1])


def check_settings(settings: GuiSettings, available: Sequence[str]) -> None:
    """Refuse bad ``--gui-*`` / ``--record`` values before anything runs (one line each)."""
    if settings.shade not in SHADES:
        raise UserError(f"--gui-shade {settings.shade}: choose from {', '.join(SHADES)}")
    for name in settings.swarms or ():
        if name not in available:
            raise UserError(
                f"--gui-swarms: {name!r} is not among the run's swarms; choose from "
                f"{', '.join(available)} or all"
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
        given = os.environ["DISPLAY"]
        if not display_answers(given):  # sumo-gui would retry for a minute, in 180 lines
            raise UserError(
                f"{flag}: the display DISPLAY={given} does not answer (an X server gone, as "
                "after an ssh -X session ended); unset DISPLAY to draw off-screen, or set it to "
                "a running X server"
            )
        yield given
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


def display_answers(name: str, timeout_s: float = 3.0) -> bool:
    """Whether the X display ``name`` (``:0``, ``unix:1``, ``host:10.0``) accepts a
    connection: its local socket ``/tmp/.X11-unix/X<n>`` (or abstract socket), else TCP port
    ``6000 + n`` of its host."""
    import re
    import socket

    found = re.fullmatch(r"(?P<host>[^:]*):(?P<n>\d+)(?:\.\d+)?", name.strip())
    if found is None:
        return False
    host, n = found["host"], int(found["n"])
    if host in ("", "unix"):
        for address in (f"/tmp/.X11-unix/X{n}", f"\0/tmp/.X11-unix/X{n}"):
            with contextlib.suppress(OSError), socket.socket(socket.AF_UNIX) as sock:
                sock.settimeout(timeout_s)
                sock.connect(address)
                return True
        if host == "unix":
            return False
        host = "localhost"
    with contextlib.suppress(OSError), socket.create_connection((host, 6000 + n), timeout_s):
        return True
    return False


def importance_rgba(value: float) -> tuple[int, int, int, int]:
    """A cell's fill: transparent yellow at importance 0 to half-transparent red at 1 (on a
    square-root scale, which separates the low values most cells have), light enough that the
    roads' speed colours and the vehicles show through."""
    v = float(np.sqrt(np.clip(np.nan_to_num(value), 0.0, 1.0)))
    return (255, int(220 * (1 - v)), 0, int(25 + 105 * v))


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
        self.shown = list(settings.swarms) if settings.swarms else default_swarms(swarms)
        order = self.shown + [n for n in swarms if n not in self.shown]  # shown: first colours
        self.colours = {n: SWARM_COLOURS[s % len(SWARM_COLOURS)] for s, n in enumerate(order)}
        self.source = None
        self.frames: list[Path] = []
        self._tmp = None
        self._frames_dir = settings.frames_dir
        if settings.record is not None and self._frames_dir is None:
            from twin.resources import scratch_dir

            self._tmp = tempfile.TemporaryDirectory(prefix="twin-frames-", dir=scratch_dir())
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
        return f"gui: drones {shown}; " + "; ".join(self.key())

    def key(self) -> list[str]:
        """What the cells and roads mean (the header's last lines)."""
        whose = f"{self.shown[0]} believes" if self.settings.shade == "belief" else "true"
        return [
            f"cells: importance {whose} (yellow low, red high), obstacles grey",
            "roads: speed (grey free flow, orange slow, dark red stopped); vehicles: dark marks",
        ]

    def clock_text(self, k: int) -> str:
        """The header's clock: simulated time of day and step, e.g. ``07:35:00  step 7/20``."""
        clock = self.source.clock(k) if hasattr(self.source, "clock") else None
        step = f"step {k}/{self.source.horizon}"
        return f"{clock}  {step}" if clock else step

    def attach(self, source) -> None:
        """Draw on ``source``'s SUMO run (its session starts with the GUI settings)."""
        source.gui = self.settings
        self.source = source
        self._ready = False
        self.settings.metres_per_px = self._metres_per_px(len(self._legend_rows()))

    def _metres_per_px(self, rows: int) -> float:
        """The view's metres per pixel: the grid and a header of ``rows`` legend rows (plus the
        key's two) fitted in the window less sumo-gui's bars."""
        g, grid = self.source.geometry, self.source.grid
        w, h = self.settings.window
        header = (rows + 2.5) * ROW_PX
        return max(
            grid.ny * g.cell_m / (w - BARS_PX[0]), grid.nx * g.cell_m / (h - BARS_PX[1] - header)
        )

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
        rows = self._legend_rows()
        header = (len(rows) + 2.5) * ROW_PX * self._metres_per_px(len(rows))
        view = traci.gui.DEFAULT_VIEW
        traci.gui.setBoundary(
            view, g.x0, g.y_top - grid.nx * c, g.x0 + grid.ny * c, g.y_top + header
        )
        self.view_boundary = traci.gui.getBoundary(view)
        (xmin, _), (xmax, _) = self.view_boundary
        self._draw_header(rows, (xmax - xmin) / (self.settings.window[0] - BARS_PX[0]))
        self._fills = {}
        self._belief = np.zeros(grid.shape)
        self._drones: set[str] = set()
        self._incidents: set[str] = set()
        self._ready = True

    def _legend_rows(self) -> list[list[str]]:
        """The header's rows of legend entries: the clock first, then the shown swarms, wrapped
        where the view ends right of the grid's left edge (the view centres the grid, so the
        room depends on the rows: wrapped again until their number holds)."""
        rows = self._wrap(self.settings.window[0] - BARS_PX[0])
        for _ in range(3):
            view_px = self.settings.window[0] - BARS_PX[0]
            grid_px = self.source.grid.ny * self.source.geometry.cell_m
            grid_px /= self._metres_per_px(len(rows))
            wrapped = self._wrap(grid_px + (view_px - grid_px) / 2 - ROW_PX)
            if len(wrapped) == len(rows):
                return wrapped
            rows = wrapped
        return rows

    def _wrap(self, width: float) -> list[list[str]]:
        """The clock and the shown swarms' legend entries in rows of ``width`` pixels."""
        rows: list[list[str]] = [[CLOCK]]
        used = _text_px(self.clock_text(self.source.horizon)) + 2 * ROW_PX
        for name in self.shown:
            need = ROW_PX + _text_px(name) + ROW_PX
            if used + need > width and rows[-1]:
                rows.append([])
                used = 0
            rows[-1].append(name)
            used += need
        return rows

    def _draw_header(self, rows: list[list[str]], per_px: float) -> None:
        """The clock, a coloured square and the name of each shown swarm, and the key, as
        POIs whose type sumo-gui writes under them (the POI itself transparent)."""
        traci, g = self._traci(), self.source.geometry
        clear = (0, 0, 0, 0)
        lift = 0.6 * TEXT_PX * per_px  # sumo-gui writes a POI's type this far below it

        def text(pid: str, words: str, x: float, y: float) -> None:
            half = _text_px(words) / 2 * per_px
            traci.poi.add(pid, x + half, y + lift, clear, poiType=words, layer=130)

        y = g.y_top + (len(rows) + 1.75) * ROW_PX * per_px
        for row in rows:
            x = g.x0
            for entry in row:
                if entry == CLOCK:
                    words = self.clock_text(0)
                    text(CLOCK, words, x, y)
                    x += (_text_px(self.clock_text(self.source.horizon)) + 2 * ROW_PX) * per_px
                    continue
                side = 0.6 * ROW_PX * per_px
                square = [(x, y - side / 2), (x + side, y - side / 2), (x + side, y + side / 2),
                          (x, y + side / 2)]  # fmt: skip
                traci.polygon.add(
                    f"legend_{entry}", square, self.colours[entry], fill=True, layer=130
                )
                text(f"legend_name_{entry}", entry, x + side + 0.4 * ROW_PX * per_px, y)
                x += (ROW_PX + _text_px(entry) + ROW_PX) * per_px
            y -= ROW_PX * per_px
        for n, line in enumerate(self.key()):
            text(f"legend_key_{n}", line, g.x0, y)
            y -= ROW_PX * per_px

    def __call__(self, k: int, positions: Mapping[str, np.ndarray], importance: np.ndarray) -> None:
        if self.source is None:
            return
        if not self._ready:
            self._setup()
        traci, g, grid = self._traci(), self.source.geometry, self.source.grid
        traci.poi.setType(CLOCK, self.clock_text(k))
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
        self._mark_incidents(k)
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

    def _mark_incidents(self, k: int) -> None:
        """Each incident applied in the simulation, red at its cell on the steps monitoring
        counts it (``onset_step`` .. ``end_step``, as incidents.json and the report say)."""
        info = getattr(self.source, "incidents_info", None)
        if info is None:
            return
        traci, g = self._traci(), self.source.geometry
        for n, rec in enumerate(info()):
            key = f"incident_{n}"
            steps = rec.get("onset_step"), rec.get("end_step")
            counted = None not in steps and steps[0] <= k <= steps[1]
            active = rec.get("applied_s") is not None and counted
            cell = rec.get("cell")  # [-1, -1]: an edge the grid leaves out
            placed = isinstance(cell, (list, tuple)) and len(cell) == 2 and min(cell) >= 0
            if active and key not in self._incidents and placed:
                x, y = g.cell_center(cell[0], cell[1])
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
            from twin.outputs import make_parent

            write_video(make_parent(self.settings.record, "--record"), frames)
            return self.settings.record
        finally:
            if self._tmp is not None:
                self._tmp.cleanup()
                self._tmp = None


def _text_px(words: str) -> float:
    """The width in pixels of ``words`` as sumo-gui writes a POI type (about 7.2 a character
    at ``poiType_size="60"``, measured on its screenshots)."""
    return 7.2 * len(words)


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

        try:
            writer = imageio_ffmpeg.write_frames(
                str(tmp), (w, h), fps=fps, codec="libx264", macro_block_size=2,
                output_params=["-f", "mp4"], ffmpeg_log_level="error",
            )  # fmt: skip
            writer.send(None)
            for im in images:
                writer.send(im)
            writer.close()
        except OSError as exc:
            if exc.errno is not None:  # the disk's, said as such by the caller
                raise
            said = str(exc.args[0] if exc.args else exc).split("FFMPEG COMMAND")[0]
            text = " ".join(said.split())[:160]
            raise UserError(
                f"--record {path}: the video encoder ({imageio_ffmpeg.get_ffmpeg_exe()}) failed"
                f" ({text}); record a GIF instead (--record FILE.gif), or fix the encoder "
                "($IMAGEIO_FFMPEG_EXE names another)"
            ) from None
        if tmp.stat().st_size == 0:
            raise UserError(
                f"--record {path}: the video encoder ({imageio_ffmpeg.get_ffmpeg_exe()}) wrote "
                "nothing; record a GIF instead (--record FILE.gif), or fix the encoder "
                "($IMAGEIO_FFMPEG_EXE names another)"
            )

    atomic_write(Path(path), write)
