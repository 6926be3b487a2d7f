"""Belief models: a swarm's picture of the city per cell and step, and how good it is.

Three models over one run, for one swarm (numpy only):

- ``last-seen``: the last importance a drone saw in its field of view, 0 before any sighting
  (the belief map of :mod:`twin.monitoring`, same numbers); no stated uncertainty.
- ``history``: per cell and step (time of day), the mean importance of earlier days' runs
  (a :class:`History`), with their standard deviation; needs no drones.
- ``nowcast``: the history fused with the drones' sightings by a per-cell Kalman filter on the
  deviation from the history mean, ``d^{k+1} = rho d^k + w`` with
  ``Var(w) = (1 - rho^2) var^{k+1}`` (the prior stays near the history's variance), ``rho``
  the history's lag-1 autocorrelation of deviations, and a measurement ``z = observed - mean``
  on every cell a drone's recorded sighting covers, of the variance the way the sighting is
  made gives (:class:`SightingModel`: a drone that counts every vehicle of a cell reads its
  true importance, variance 0 but for a floor).
- ``nowcast+detectors``: the same filter also updated, at every step, on each cell that fixed
  detectors read (:class:`DetectorObservations`, the importance of a station's reading by the
  MFD), less the station's bias, a measurement of the station's variance: both learned from
  earlier days' runs with the same stations (:class:`DetectorCalibration`, kept in the
  history), else bias 0 and ``detector_var``. Without drones (swarm :data:`DETECTORS_ONLY`)
  it is the reference for what the drones add.

Each model gives a mean and a standard deviation per step and cell (``(T+1, nx*ny)``; NaN
std: none stated), the mean clipped to [0, 1]. :func:`belief_scores` scores one against the
truth: the importance-weighted MAE of :mod:`twin.monitoring`, calibration of the 90% interval,
congestion events known (belief >= threshold while the event lasts) with their latency, and
false alarms (onsets of belief >= threshold where the truth is below it) per hour.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from twin.errors import UserError
from twin.files import not_a_file
from twin.grid import Grid
from twin.mfd import PRIOR_K_C
from twin.monitoring import MonitorSettings, congestion_events
from twin.notices import notify
from twin.seeds import MAX_SEED, is_seed

MODELS = ("last-seen", "history", "nowcast", "nowcast+detectors")
#: Row name of the history-only reference (no drones).
NO_DRONES = "(no drones)"
#: Row name of the detectors-only reference (history and fixed detectors, no drones).
DETECTORS_ONLY = "(detectors only)"
#: Variance of a sighting that reads the cell's true importance (a drone that counts every
#: vehicle of the cell): 0 but for numerics, std 0.001, a tenth of the smallest history std the
#: filter uses (VAR_FLOOR), so that a sighting moves the belief 99% of the way or more.
SIGHTING_VAR_FLOOR = 1e-6
#: Variance of a detector station's reading of its cell's importance when the history has no
#: calibration of it: the mean square error of the readings of 48 virtual loop stations against
#: their cells' true importance on validation SUMO seed 100 of the default rush hour (0.0029,
#: bias -0.027 included; docs/beliefs.md).
DEFAULT_DETECTOR_VAR = 3e-3
#: Smallest per-cell history variance used by the filter (std 0.01).
VAR_FLOOR = 1e-4
#: Largest autocorrelation used (keeps some process noise on every cell).
RHO_MAX = 0.99
#: Largest neighbour correlation used by the spatial coupling.
CORR_MAX = 0.95
#: Half-width of the 90% interval in standard deviations.
Z90 = 1.6448536269514722
HISTORY_VERSION = 1


@dataclass(frozen=True, eq=False)
class DetectorCalibration:
    """Per detector station (its cell, flat index): the bias and variance of its readings of
    the cell's importance against the cell's true importance on earlier days, and how many
    readings gave them (:func:`fit_detector_calibration`)."""

    cells: np.ndarray  # (n,) flat cell indices, distinct, sorted, n >= 1
    bias: np.ndarray  # (n,)
    var: np.ndarray  # (n,) >= SIGHTING_VAR_FLOOR
    n_readings: np.ndarray  # (n,)

    def at(self, cells: np.ndarray, default_var: float) -> tuple[np.ndarray, np.ndarray]:
        """``(bias, var)`` of the stations at ``cells``: the calibrated ones', else bias 0
        and ``default_var`` (a station the earlier days did not have)."""
        cells = np.asarray(cells, dtype=np.int64)
        at = np.minimum(np.searchsorted(self.cells, cells), len(self.cells) - 1)
        known = self.cells[at] == cells
        bias = np.where(known, self.bias[at], 0.0)
        var = np.where(known, self.var[at], default_var)
        return bias, var


def fit_detector_calibration(days) -> DetectorCalibration | None:
    """Each station cell's bias (mean of reading minus truth) and variance (``ddof = 1``, at
    least :data:`SIGHTING_VAR_FLOOR`) over earlier days: ``days`` gives
    ``(DetectorObservations, truth (T+1, nx, ny))`` pairs. Cells with fewer than 2 readings
    are left out; None when no cell has 2."""
    residuals: dict[int, list[np.ndarray]] = {}
    for observations, truth in days:
        t = np.asarray(truth, dtype=np.float64).reshape(len(truth), -1)
        steps = min(len(t), len(observations.values))
        r = observations.values[:steps] - t[:steps, observations.cells]
        for col, cell in enumerate(observations.cells):
            residuals.setdefault(int(cell), []).append(r[:, col][np.isfinite(r[:, col])])
    cells, bias, var, count = [], [], [], []
    for cell in sorted(residuals):
        r = np.concatenate(residuals[cell])
        if len(r) < 2:
            continue
        cells.append(cell)
        bias.append(r.mean())
        var.append(max(r.var(ddof=1), SIGHTING_VAR_FLOOR))
        count.append(len(r))
    if not cells:
        return None
    return DetectorCalibration(
        np.array(cells, dtype=np.int64), np.array(bias), np.array(var), np.array(count)
    )


#: The arrays of a :class:`DetectorCalibration` in a history file (``detector_<name>``).
CALIBRATION_KEYS = ("cells", "bias", "var", "n_readings")


def _calibration(path: Path, arrays: dict, n_cells: int, fix: str) -> DetectorCalibration | None:
    """The calibration read from a history file's ``detector_*`` arrays (None when it has
    none); anything inconsistent is one :class:`UserError` line."""
    if not arrays:
        return None
    if set(arrays) != set(CALIBRATION_KEYS):
        missing = sorted(set(CALIBRATION_KEYS) - set(arrays))[0]
        raise UserError(f"{path}: detector calibration without detector_{missing}; {fix}")
    shapes = {a.shape for a in arrays.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 1 or not next(iter(shapes))[0]:
        raise UserError(f"{path}: detector calibration arrays are not of one length n >= 1; {fix}")
    if any(a.dtype.kind not in "fiu" for a in arrays.values()):
        raise UserError(f"{path}: detector calibration holds values that are not numbers; {fix}")
    cells, n = arrays["cells"], arrays["n_readings"]
    bias, var = (np.asarray(arrays[k], dtype=np.float64) for k in ("bias", "var"))
    checks = (
        ("detector_cells", cells, (cells == np.round(cells)) & (cells >= 0) & (cells < n_cells),
         f"a cell index in 0 .. {n_cells - 1}"),
        ("detector_bias", bias, np.isfinite(bias) & (np.abs(bias) <= 1), "a number in [-1, 1]"),
        ("detector_var", var, np.isfinite(var) & (var > 0) & (var <= 1), "a number in (0, 1]"),
        ("detector_n_readings", n, (n == np.round(n)) & (n >= 2), "a whole number >= 2"),
    )  # fmt: skip
    for name, values, ok, want in checks:
        if not ok.all():
            at = int(np.flatnonzero(~ok)[0])
            raise UserError(f"{path}: {name}[{at}] = {values[at]} is not {want}; {fix}")
    cells = cells.astype(np.int64)
    if np.any(np.diff(cells) <= 0):
        raise UserError(f"{path}: detector_cells are not distinct and sorted; {fix}")
    return DetectorCalibration(cells, bias, var, n.astype(np.int64))


#: The fix of a history that does not fit the run.
HISTORY_FIX = "build the history from runs of the same scenario and options"


@dataclass(frozen=True)
class History:
    """Per step and cell: mean and variance of earlier days' importance; per cell ``rho``."""

    mean: np.ndarray  # (T+1, nx, ny)
    var: np.ndarray  # (T+1, nx, ny)
    rho: np.ndarray  # (nx, ny) in [0, RHO_MAX]
    obstacles: np.ndarray  # (nx, ny) bool
    n_runs: int
    step_s: float | None = None
    begin: str | None = None
    traffic_seeds: tuple[int, ...] = ()  # SUMO seeds of the runs (when known)
    sources: tuple[str, ...] = ()
    #: correlation of deviations between 4-neighbour free cells (same step), pooled
    neighbour_corr: float = 0.0
    #: the detector stations' calibration on these days (None: runs without detectors)
    detectors: DetectorCalibration | None = None
    #: the file it was read from (None: built in memory)
    path: str | None = field(default=None, compare=False)

    @property
    def horizon(self) -> int:
        return self.mean.shape[0] - 1

    @property
    def shape(self) -> tuple[int, int]:
        return self.obstacles.shape

    def save(self, path: Path) -> None:
        """Write the history as ``.npz`` (arrays plus a JSON ``info``)."""
        info = {
            "version": HISTORY_VERSION,
            "n_runs": self.n_runs,
            "step_s": self.step_s,
            "begin": self.begin,
            "traffic_seeds": list(self.traffic_seeds),
            "sources": list(self.sources),
            "neighbour_corr": self.neighbour_corr,
        }
        stations = {}
        if self.detectors is not None:
            stations = {f"detector_{k}": getattr(self.detectors, k) for k in CALIBRATION_KEYS}
        with open(path, "wb") as fh:
            np.savez_compressed(
                fh,
                mean=self.mean.astype(np.float32),
                var=self.var.astype(np.float32),
                rho=self.rho.astype(np.float32),
                obstacles=self.obstacles,
                info=np.array(json.dumps(info)),
                **stations,
            )

    @classmethod
    def load(cls, path: Path) -> History:
        """Read and check a history file; any problem is one :class:`UserError` line."""
        path = Path(path)
        fix = "build it again with `twin history --from RUN_DIR ... --out FILE`"
        why = not_a_file(path)
        if why == "does not exist":
            raise UserError(f"{path}: no such history file; {fix}")
        if why is not None:
            raise UserError(f"{path}: {why} (a history file of `twin history`)")
        try:
            with np.load(path, allow_pickle=False) as data:
                lacking = [k for k in HISTORY_ARRAYS if k not in data.files]
                if lacking:  # (numpy's KeyError says it in words of its own)
                    raise UserError(f"{path}: not a twin history (no array {lacking[0]!r}); {fix}")
                arrays = {k: data[k] for k in HISTORY_ARRAYS}
                stations = {k: data[f"detector_{k}"] for k in CALIBRATION_KEYS if
                            f"detector_{k}" in data.files}  # fmt: skip
        except UserError:
            raise
        except Exception as exc:
            raise UserError(f"{path}: not a readable .npz ({type(exc).__name__}); {fix}") from None
        try:
            info = json.loads(str(arrays["info"]))
            assert isinstance(info, dict)
        except Exception:
            raise UserError(f"{path}: its info is not valid JSON; {fix}") from None
        if info.get("version") != HISTORY_VERSION:
            raise UserError(
                f"{path}: history version = {info.get('version')!r}, expected "
                f"{HISTORY_VERSION}; {fix}"
            )
        for name in ("mean", "var", "rho"):
            kind = arrays[name].dtype.kind
            if kind not in "fiub":
                raise UserError(
                    f"{path}: {name} holds {arrays[name].dtype} values, not real numbers; {fix}"
                )
        mean, var, rho = (np.asarray(arrays[k], dtype=np.float64) for k in ("mean", "var", "rho"))
        obstacles = np.asarray(arrays["obstacles"]).astype(bool)
        if mean.ndim != 3 or var.shape != mean.shape or mean.shape[0] < 2:
            raise UserError(
                f"{path}: mean {mean.shape} and var {var.shape} are not (T+1, nx, ny) "
                f"arrays of one shape; {fix}"
            )
        if obstacles.shape != mean.shape[1:] or rho.shape != mean.shape[1:]:
            raise UserError(
                f"{path}: obstacles {obstacles.shape} or rho {rho.shape} do not match the "
                f"grid {mean.shape[1]} x {mean.shape[2]}; {fix}"
            )
        for name, arr, lo, hi in (("mean", mean, 0, 1), ("var", var, 0, 1), ("rho", rho, 0, 1)):
            bad = ~np.isfinite(arr) | (arr < lo) | (arr > hi)
            if bad.any():
                at = tuple(int(x) for x in np.argwhere(bad)[0])
                raise UserError(
                    f"{path}: {name} = {arr[at]} at {at} is not a number in [{lo}, {hi}]; {fix}"
                )
        seeds = info.get("traffic_seeds")
        if not isinstance(seeds, list) or not all(
            isinstance(x, int) and not isinstance(x, bool) for x in seeds
        ):
            raise UserError(
                f"{path}: traffic_seeds = {seeds!r} is not a list of the SUMO seeds it was built "
                f"from (needed to refuse a history that holds an evaluated day); {fix}"
            )
        wrong = [x for x in seeds if not is_seed(x)]
        if wrong:
            raise UserError(
                f"{path}: traffic_seeds holds {str(wrong[0])[:30]}, not a SUMO seed (0 .. "
                f"{MAX_SEED}); {fix}"
            )
        n_runs, sources = info.get("n_runs"), info.get("sources") or []
        if not isinstance(n_runs, int) or isinstance(n_runs, bool) or n_runs < 1:
            raise UserError(f"{path}: n_runs = {n_runs!r} is not a whole number >= 1; {fix}")
        if len(set(seeds)) != len(seeds) or len(seeds) > n_runs:
            raise UserError(
                f"{path}: traffic_seeds = {str(seeds)[:60]} are not distinct seeds of its "
                f"n_runs = {n_runs} days; {fix}"
            )
        if not isinstance(sources, list) or len(sources) != (n_runs if sources or seeds else 0):
            raise UserError(
                f"{path}: sources = {str(sources)[:60]} do not name its n_runs = {n_runs} days "
                f"(one each; none only in a history without traffic seeds); {fix}"
            )
        if sources and len(seeds) != n_runs:  # `twin history` records every day's seed
            raise UserError(
                f"{path}: traffic_seeds = {str(seeds)[:60]} do not give the seed of each of its "
                f"n_runs = {n_runs} days (needed to refuse a history that holds an evaluated "
                f"day); {fix}"
            )
        step_s, begin = info.get("step_s"), info.get("begin")
        if step_s is not None and not (
            isinstance(step_s, (int, float)) and not isinstance(step_s, bool) and step_s > 0
            and math.isfinite(step_s)
        ):  # fmt: skip
            raise UserError(
                f"{path}: step_s = {str(step_s)[:40]!r} is not a step in seconds > 0 (nor null, "
                f"a synthetic history's); {fix}"
            )
        if begin is not None and not isinstance(begin, str):
            raise UserError(
                f"{path}: begin = {str(begin)[:40]!r} is not a clock time (text, e.g. "
                f'"07:00:00"), nor null; {fix}'
            )
        corr = info.get("neighbour_corr", 0.0)
        if not isinstance(corr, (int, float)) or not 0.0 <= corr <= 1.0:
            raise UserError(f"{path}: neighbour_corr = {corr!r} is not a number in [0, 1]; {fix}")
        return cls(
            mean,
            var,
            rho,
            obstacles,
            n_runs,
            None if step_s is None else float(step_s),
            begin,
            tuple(seeds),
            tuple(str(s) for s in info.get("sources") or ()),
            float(corr),
            _calibration(path, stations, obstacles.size, fix),
            str(path),
        )

    def check_grid(self, where: Path | str, obstacles: np.ndarray) -> None:
        """Refuse (one line naming ``where``) a history of another grid or other obstacles."""
        nx, ny = self.shape
        if tuple(obstacles.shape) != (nx, ny):
            raise UserError(
                f"{where}: history grid {nx} x {ny} differs from the run's "
                f"{obstacles.shape[0]} x {obstacles.shape[1]}; {HISTORY_FIX}"
            )
        if not np.array_equal(obstacles, self.obstacles):
            i, j = (int(x) for x in np.argwhere(obstacles != self.obstacles)[0])
            raise UserError(
                f"{where}: history obstacles differ from the run's (first at cell ({i}, {j})); "
                f"{HISTORY_FIX}"
            )

    def check_horizon(self, where: Path | str, horizon: int) -> None:
        """Refuse (one line naming ``where``) a history of another horizon."""
        if horizon != self.horizon:
            raise UserError(
                f"{where}: history horizon T = {self.horizon} differs from the run's T = "
                f"{horizon}; {HISTORY_FIX}"
            )

    def named(self, swarm: str) -> str:
        """How a swarm's refusal names this history: its file (or the swarm's history)."""
        return (
            f"{self.path} (the history of swarm {swarm})"
            if self.path
            else (f"the history of swarm {swarm}")
        )

    def check_matches(
        self,
        where: Path | str,
        obstacles: np.ndarray,
        horizon: int,
        step_s: float | None = None,
        begin: str | None = None,
        traffic_seeds: Sequence[int] = (),
    ) -> None:
        """Refuse (one line naming ``where``) a history whose grid, horizon, step length or
        start differs from the run's, or that was built from one of the run's traffic seeds."""
        self.check_grid(where, obstacles)
        self.check_horizon(where, horizon)
        fix = HISTORY_FIX
        if step_s is not None and self.step_s is not None and abs(step_s - self.step_s) > 1e-9:
            raise UserError(
                f"{where}: history step {self.step_s:g} s differs from the run's {step_s:g} s; "
                f"{fix}"
            )
        if begin is not None and self.begin is not None and begin != self.begin:
            raise UserError(f"{where}: history starts at {self.begin}, the run at {begin}; {fix}")
        unknown = self.n_runs - len(self.traffic_seeds)
        if traffic_seeds and unknown:
            notify(
                f"twin: notice: {where}: {unknown} of the history's {self.n_runs} days have no "
                "recorded SUMO seed, so twin cannot check that none of them is a day this run "
                "evaluates on"
            )
        shared = sorted(set(self.traffic_seeds) & set(traffic_seeds))
        if shared:  # the run's other seeds are not known here: no number that may clash
            raise UserError(
                f"{where}: history built from traffic seed {shared[0]}, which this run "
                "evaluates on; build it from SUMO seeds the run does not use (for a run of "
                "--sumo-seed s and --seeds n, from --sumo-seed s+n on)"
            )


@dataclass(frozen=True, eq=False)
class SightingModel:
    """How a drone's sighting of a cell is made, and so the variance of the importance it reads.

    A drone counts the vehicles of each cell of its field of view over the step's ``reads``
    instants; the density ``k = n / (reads L)`` (``L`` the cell's lane-km) gives the importance
    by the MFD, ``T = 1 - exp(-k / k_c)`` (Def. 2 on Underwood's curve, :mod:`twin.mfd`).

    - Every vehicle counted (``count_p = 1``): the sighting is the true importance, variance 0,
      kept at ``floor`` for numerics.
    - Each vehicle seen with probability ``p = count_p`` (``[traffic.mfd] detection_p``: the
      count is binomially thinned and scaled by ``1 / p``): ``Var(k^) = k (1 - p) / (p reads
      L)``, and by the delta method (``dT/dk = (1 - T) / k_c``)

      ``Var(T^) = (1 - T)^2 (-ln(1 - T)) (1 - p) / (p k_c reads L)``,

      evaluated at the reading itself (plug-in), plus ``floor``. ``k_c`` is the MFD prior's
      (the online fit moves it: a first-order model).

    A sighting lost whole (``[faults] detection_p``, :mod:`twin.faults`) is no measurement: the
    filter is not updated on it (the ``recorded`` sightings of :func:`nowcast`), and those that
    are recorded are as exact as the count.
    """

    count_p: float = 1.0
    lane_km: np.ndarray | None = None  # (nx*ny,) lane-km per flat cell; needed when count_p < 1
    k_c: float = PRIOR_K_C
    reads: int = 1
    floor: float = SIGHTING_VAR_FLOOR

    def __post_init__(self) -> None:
        if not 0.0 < self.count_p <= 1.0:
            raise ValueError(f"count_p must lie in (0, 1], got {self.count_p}")
        if self.count_p < 1.0 and self.lane_km is None:
            raise ValueError("a thinned count (count_p < 1) needs the cells' lane_km")

    @property
    def exact(self) -> bool:
        """Whether every sighting reads the true importance (variance ``floor``)."""
        return self.count_p >= 1.0

    def variance(self, values: np.ndarray, cells: np.ndarray) -> np.ndarray:
        """Measurement variance of sightings reading ``values`` on the flat ``cells``."""
        values = np.asarray(values, dtype=np.float64)
        if self.exact:
            return np.full(values.shape, self.floor)
        p = self.count_p
        t = np.clip(values, 0.0, 1.0 - 1e-9)
        lane_km = np.asarray(self.lane_km, dtype=np.float64)[cells]
        with np.errstate(divide="ignore", invalid="ignore"):
            var = (1 - t) ** 2 * -np.log1p(-t) * (1 - p) / (p * self.k_c * self.reads * lane_km)
        return self.floor + np.where(lane_km > 0, var, 0.0)


#: How the sightings of a source that gives the drones the true map are made.
EXACT_SIGHTINGS = SightingModel()


@dataclass(frozen=True)
class DetectorObservations:
    """What fixed detectors read: per step ``k = 0..T`` and station cell, the importance of
    their reading (the mean over a cell's detectors that reported at that step), NaN where
    none did."""

    cells: np.ndarray  # (n,) flat cell indices, distinct
    values: np.ndarray  # (T+1, n)

    @classmethod
    def from_readings(cls, readings, horizon: int) -> DetectorObservations:
        """From ``(k, flat cell, importance)`` triples (several detectors per cell averaged)."""
        rows = [(int(k), int(c), float(v)) for k, c, v in readings if 0 <= k <= horizon]
        cells = np.array(sorted({c for _, c, _ in rows}), dtype=np.int64)
        total = np.zeros((horizon + 1, len(cells)))
        count = np.zeros((horizon + 1, len(cells)))
        if rows:
            k, c, v = (np.array(x) for x in zip(*rows, strict=True))
            col = np.searchsorted(cells, c)
            np.add.at(total, (k, col), v)
            np.add.at(count, (k, col), 1.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            values = np.where(count > 0, total / np.maximum(count, 1.0), np.nan)
        return cls(cells, values)


def fit_history(
    maps: Sequence[np.ndarray],
    obstacles: np.ndarray,
    step_s: float | None = None,
    begin: str | None = None,
    traffic_seeds: Sequence[int] = (),
    sources: Sequence[str] = (),
    detectors: DetectorCalibration | None = None,
) -> History:
    """The :class:`History` of ``maps`` (each ``(T+1, nx, ny)``, one per earlier day).

    Variance per step and cell with ``ddof = 1`` (0 with one run); ``rho`` per cell is the
    lag-1 autocorrelation of the deviations from the mean, pooled over runs, the value pooled
    over all cells where a cell's deviations are all zero, clipped to ``[0, RHO_MAX]``.
    """
    x = np.stack([np.asarray(m, dtype=np.float64) for m in maps])  # (R, T+1, nx, ny)
    n_runs = x.shape[0]
    mean = x.mean(axis=0)
    var = x.var(axis=0, ddof=1) if n_runs > 1 else np.zeros_like(mean)
    dev = x - mean
    a, b = dev[:, 1:], dev[:, :-1]
    num = (a * b).sum(axis=(0, 1))
    den = np.sqrt((a * a).sum(axis=(0, 1)) * (b * b).sum(axis=(0, 1)))
    pooled_den = np.sqrt((a * a).sum() * (b * b).sum())
    pooled = num.sum() / pooled_den if pooled_den > 0 else 0.0
    with np.errstate(invalid="ignore", divide="ignore"):
        rho = np.where(den > 0, num / np.where(den > 0, den, 1.0), pooled)
    rho = np.clip(rho, 0.0, RHO_MAX)
    src, dst = neighbour_pairs(Grid(np.asarray(obstacles, dtype=bool)))
    flat = dev.reshape(*dev.shape[:2], -1)
    a, b = flat[..., src], flat[..., dst]
    den = np.sqrt((a * a).sum() * (b * b).sum())
    corr = float(np.clip((a * b).sum() / den, 0.0, CORR_MAX)) if den > 0 else 0.0
    return History(
        np.clip(mean, 0.0, 1.0),
        np.clip(var, 0.0, 1.0),
        rho,
        np.asarray(obstacles, dtype=bool).copy(),
        n_runs,
        step_s,
        begin,
        tuple(int(s) for s in traffic_seeds),
        tuple(str(s) for s in sources),
        corr,
        detectors,
    )


#: The arrays every history file holds (:meth:`History.load`).
HISTORY_ARRAYS = ("mean", "var", "rho", "obstacles", "info")


#: Peak memory of a history of synthetic days (:func:`days_history`) per cell and step of each
#: day: the generator's components, its maps and the fit's copies. Measured with ``twin
#: history --dynamics`` on a 60 x 60 grid, T = 2000: 2.07 GB for 2 days, 5.63 GB for 6 (889 MB
#: a day, 123 B per cell and step), rounded up.
DAY_BYTES = 130


def days_history(days: Sequence, seeds: Sequence[int] = (), sources: Sequence[str] = ()) -> History:
    """The :class:`History` of synthetic days: each traffic source's maps ``T^0 .. T^T`` (one
    source per day, all of one grid and horizon), fitted by :func:`fit_history`. ``seeds``:
    the generator's seed of each day (recorded as the history's ``traffic_seeds``)."""
    maps = [np.stack([np.array(m, dtype=np.float64) for m in day.importance_maps()])
            for day in days]  # fmt: skip
    return fit_history(maps, days[0].grid.obstacles, traffic_seeds=seeds, sources=sources)


def neighbour_pairs(grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices ``(src, dst)`` of every ordered pair of 4-neighbour free cells."""
    free = grid.free
    idx = np.arange(grid.nx * grid.ny).reshape(grid.shape)
    src, dst = [], []
    for a, b in ((idx[:-1], idx[1:]), (idx[:, :-1], idx[:, 1:])):
        ok = free.ravel()[a] & free.ravel()[b]
        src += [a[ok], b[ok]]
        dst += [b[ok], a[ok]]
    return np.concatenate(src), np.concatenate(dst)


def _view_cells(
    grid: Grid, positions_k: np.ndarray, recorded_k: np.ndarray | None = None
) -> np.ndarray:
    """Flat indices of the free cells in the drones' fields of view at one step (``recorded_k``
    ``(N, 5)``: only the sightings that count)."""
    flat, valid = grid.view_index(positions_k)
    cells = flat[valid if recorded_k is None else valid & recorded_k]
    return np.unique(cells[grid.free.ravel()[cells]])


def last_seen(
    grid: Grid, positions: np.ndarray, observed: np.ndarray, recorded: np.ndarray | None = None
):
    """``(mean, std)`` of the last-seen belief: the last observed value, 0 before; std NaN.
    ``recorded`` ``(T+1, N, 5)``: the sightings that count (:meth:`twin.faults.FaultPlan.
    recorded`, as monitoring counts them); None: all."""
    steps = positions.shape[0]
    belief = np.zeros(grid.nx * grid.ny)
    out = np.empty((steps, grid.nx * grid.ny))
    for k in range(steps):
        flat, valid = grid.view_index(positions[k])
        cells = flat[valid if recorded is None else valid & recorded[k]]
        belief[cells] = observed[k].ravel()[cells]
        out[k] = belief
    return out, np.full_like(out, np.nan)


def history_belief(history: History, steps: int | None = None):
    """``(mean, std)`` of the history model for steps ``0 .. steps-1`` (no drones needed)."""
    steps = history.mean.shape[0] if steps is None else steps
    mean = history.mean[:steps].reshape(steps, -1)
    return mean.copy(), np.sqrt(np.maximum(history.var[:steps].reshape(steps, -1), VAR_FLOOR))


def nowcast(
    grid: Grid,
    positions: np.ndarray,
    observed: np.ndarray,
    history: History,
    meas_var: float | None = None,
    coupling: float = 0.0,
    detectors: DetectorObservations | None = None,
    detector_var: float = DEFAULT_DETECTOR_VAR,
    sighting: SightingModel = EXACT_SIGHTINGS,
    recorded: np.ndarray | None = None,
):
    """``(mean, std)`` of the history fused with the drones' sightings (module docstring),
    and with ``detectors``' readings when given: each station's reading less its bias, of its
    variance, as the history's :class:`DetectorCalibration` gives them (a station it does not
    know, or a history without one: bias 0, variance ``detector_var``); ``positions`` may
    hold no drone (``(T+1, 0, 2)``): history and detectors alone.

    The filter starts from the history's prior at step 0 (deviation 0, variance ``var^0``),
    predicts ``d <- rho d``, ``P <- rho^2 P + (1 - rho^2) var^k`` and updates every cell in
    view with ``z = observed^k - mean^k`` of the variance ``sighting`` gives
    (:class:`SightingModel`), or ``meas_var`` when given; vectorised over cells. ``recorded``
    ``(T+1, N, 5)``: only these sightings update it (a sighting lost to a fault is none).
    With ``coupling = r > 0`` each observed cell's innovation also updates its unobserved
    4-neighbours, as if their deviations had correlation ``r`` (cross-covariance
    ``r sqrt(P_n P_c)``, one neighbour at a time).
    """
    steps = positions.shape[0]
    mu = history.mean[:steps].reshape(steps, -1)
    var = np.maximum(history.var[:steps].reshape(steps, -1), VAR_FLOOR)
    rho = history.rho.ravel()
    rho2 = rho * rho
    d = np.zeros(mu.shape[1])
    p = var[0].copy()
    mean = np.empty_like(mu)
    std = np.empty_like(mu)
    src, dst = neighbour_pairs(grid) if coupling > 0 else (None, None)
    in_view = np.zeros(mu.shape[1], dtype=bool)
    if detectors is not None:
        station_bias, station_var = (
            (np.zeros(len(detectors.cells)), np.full(len(detectors.cells), detector_var))
            if history.detectors is None
            else history.detectors.at(detectors.cells, detector_var)
        )
    for k in range(steps):
        if k:
            d = rho * d
            p = rho2 * p + (1.0 - rho2) * var[k]
        cells = _view_cells(grid, positions[k], None if recorded is None else recorded[k])
        if len(cells):
            seen = observed[k].ravel()[cells]
            r = sighting.variance(seen, cells) if meas_var is None else meas_var
            innovation = seen - mu[k, cells] - d[cells]
            s = p[cells] + r
            p_before = p[cells].copy()
            gain = p[cells] / s
            d[cells] += gain * innovation
            p[cells] *= 1.0 - gain
            if src is not None:
                in_view[:] = False
                in_view[cells] = True
                at = np.full(mu.shape[1], -1)
                at[cells] = np.arange(len(cells))
                pick = in_view[src] & ~in_view[dst]
                for a, b in zip(src[pick], dst[pick], strict=True):  # few pairs per step
                    c = at[a]
                    cov = coupling * np.sqrt(p[b] * p_before[c])
                    d[b] += cov / s[c] * innovation[c]
                    p[b] -= cov * cov / s[c]
        if detectors is not None and k < len(detectors.values):
            read = np.isfinite(detectors.values[k])
            cells = detectors.cells[read]
            innovation = detectors.values[k, read] - station_bias[read] - mu[k, cells] - d[cells]
            gain = p[cells] / (p[cells] + station_var[read])
            d[cells] += gain * innovation
            p[cells] *= 1.0 - gain
        mean[k] = np.clip(mu[k] + d, 0.0, 1.0)
        std[k] = np.sqrt(p)
    return mean, std


class NowcastFilter:
    """The ``nowcast`` filter step by step, for a swarm that plans on it (:func:`nowcast` runs
    the same arithmetic over a whole run, without coupling or detectors).

    :meth:`advance` moves to step ``k`` (the prior of step 0, else the prediction ``d <- rho
    d``, ``P <- rho^2 P + (1 - rho^2) var^k``); :meth:`observe` updates the cells in view with
    their observed importance, of the variance ``sighting`` gives (``meas_var`` when given);
    :meth:`predicted` is the prior of step ``k + 1``.
    """

    def __init__(
        self,
        history: History,
        meas_var: float | None = None,
        sighting: SightingModel = EXACT_SIGHTINGS,
    ):
        steps = history.mean.shape[0]
        self.mu = history.mean.reshape(steps, -1)
        self.var = np.maximum(history.var.reshape(steps, -1), VAR_FLOOR)
        self.rho = history.rho.ravel()
        self.rho2 = self.rho * self.rho
        self.meas_var = None if meas_var is None else float(meas_var)
        self.sighting = sighting
        self.k = -1
        self.d = np.zeros(self.mu.shape[1])
        self.p = self.var[0].copy()

    def advance(self, k: int) -> None:
        """Predict forward to step ``k`` (``k = 0``: the prior; steps skipped, with no
        sighting, are predicted one by one)."""
        if k == 0:
            self.d[:] = 0.0
            self.p = self.var[0].copy()
            self.k = 0
            return
        if k <= self.k:
            raise ValueError(f"nowcast filter at step {self.k} cannot move back to step {k}")
        for step in range(self.k + 1, k + 1):
            self.d = self.rho * self.d
            self.p = self.rho2 * self.p + (1.0 - self.rho2) * self.var[step]
        self.k = k

    def observe(self, cells: np.ndarray, values: np.ndarray) -> None:
        """Update the (distinct, free) flat ``cells`` on their observed importance ``values``."""
        if not len(cells):
            return
        innovation = values - self.mu[self.k, cells] - self.d[cells]
        gain = self.p[cells] / (self.p[cells] + self.measurement_variance(values, cells))
        self.d[cells] += gain * innovation
        self.p[cells] *= 1.0 - gain

    def measurement_variance(self, values: np.ndarray, cells: np.ndarray) -> np.ndarray:
        """Variance of sightings reading ``values`` on the flat ``cells``."""
        if self.meas_var is not None:
            return np.full(np.shape(values), self.meas_var)
        return self.sighting.variance(values, cells)

    def mean(self) -> np.ndarray:
        """``(nx*ny,)`` the belief of step ``k``, clipped to [0, 1]."""
        return np.clip(self.mu[self.k] + self.d, 0.0, 1.0)

    def std(self) -> np.ndarray:
        return np.sqrt(self.p)

    def predicted(self) -> tuple[np.ndarray, np.ndarray]:
        """``(mean, var)`` of step ``k + 1`` before any sighting (the mean clipped)."""
        k = self.k + 1
        d = self.rho * self.d
        p = self.rho2 * self.p + (1.0 - self.rho2) * self.var[k]
        return np.clip(self.mu[k] + d, 0.0, 1.0), p


def error_curve(mean: np.ndarray, truth: np.ndarray, grid: Grid, floor: float) -> np.ndarray:
    """``(T+1,)`` importance-weighted MAE over free cells (as :mod:`twin.monitoring`)."""
    free = grid.free.ravel()
    out = np.empty(mean.shape[0])
    for k in range(mean.shape[0]):  # per step, summed as monitoring sums: equal to the bit
        true = truth[k].ravel()
        w = np.maximum(true, floor)[free]
        out[k] = float((w * np.abs(mean[k][free] - true[free])).sum() / w.sum())
    return out


def belief_scores(
    mean: np.ndarray,
    std: np.ndarray,
    truth: np.ndarray,
    grid: Grid,
    settings: MonitorSettings | None = None,
    step_s: float | None = None,
    events: pd.DataFrame | None = None,
) -> dict:
    """The columns of one belief model: belief error (mean over k = 1..T), calibration (share of
    free cell-steps k = 1..T whose truth lies in the clipped 90% interval; NaN without std),
    events, % known and median latency (steps, minutes), false alarms and per hour."""
    settings = settings or MonitorSettings()
    steps = mean.shape[0]
    truth = np.asarray(truth[:steps])  # dtype kept: same sums as monitoring
    if events is None:
        events = congestion_events(truth, grid, settings.threshold, settings.min_duration)
    curve = error_curve(mean, truth, grid, settings.weight_floor)
    free = grid.free.ravel()
    true = truth.reshape(steps, -1)
    if np.isnan(std).all():
        calibration = np.nan
    else:
        lo = np.clip(mean - Z90 * std, 0.0, 1.0)[1:, free]
        hi = np.clip(mean + Z90 * std, 0.0, 1.0)[1:, free]
        t = true[1:, free]
        calibration = float(((t >= lo - 1e-9) & (t <= hi + 1e-9)).mean()) if t.size else np.nan
    hot = mean >= settings.threshold
    cell = events["i"].to_numpy(np.int64) * grid.ny + events["j"].to_numpy(np.int64)
    onset = events["onset"].to_numpy(np.int64)
    duration = events["duration"].to_numpy(np.int64)
    latency = []
    for c, a, n in zip(cell, onset, duration, strict=True):
        hit = np.flatnonzero(hot[a : a + n, c])
        if len(hit):
            latency.append(int(hit[0]))
    alarms = hot & (true < settings.threshold) & free
    starts = alarms.copy()
    starts[1:] &= ~alarms[:-1]
    n_alarms = int(starts.sum())
    hours = steps * step_s / 3600.0 if step_s else None
    row = {
        "belief_error": float(curve[1:].mean()) if steps > 1 else np.nan,
        "calibration_90": calibration,
        "events": len(cell),
        "pct_events_known": 100.0 * len(latency) / len(cell) if len(cell) else np.nan,
        "latency_median_steps": float(np.median(latency)) if latency else np.nan,
        "false_alarms": n_alarms,
        "false_alarms_per_hour": n_alarms / hours if hours else np.nan,
    }
    row["latency_median_min"] = row["latency_median_steps"] * step_s / 60.0 if step_s else np.nan
    return row


#: Columns of ``belief_models.csv`` besides swarm and model.
BELIEF_COLUMNS = (
    "belief_error",
    "calibration_90",
    "events",
    "pct_events_known",
    "latency_median_steps",
    "latency_median_min",
    "false_alarms",
    "false_alarms_per_hour",
)


def run_sensing(result) -> tuple[SightingModel, np.ndarray | None]:
    """How a run's sightings were made (``result.extra["sighting"]``, set by the experiment
    from its traffic source; exact when absent) and which of them count (``(T+1, N, 5)``, the
    run's scripted faults, :meth:`twin.faults.FaultPlan.recorded`; None: all)."""
    sighting = (getattr(result, "extra", None) or {}).get("sighting") or EXACT_SIGHTINGS
    faults = getattr(result, "faults", None)
    positions = result.positions
    recorded = None if faults is None else faults.recorded(result.seed, *positions.shape[1:3])
    return sighting, recorded


def belief_table(
    result,
    history: History,
    settings: MonitorSettings | None = None,
    step_s: float | None = None,
    meas_var: float | None = None,
    spatial: bool = False,
    detector_var: float = DEFAULT_DETECTOR_VAR,
) -> pd.DataFrame:
    """One row per swarm x model (last-seen, nowcast) of one seed, plus the history-only
    reference row (swarm ``(no drones)``, model ``history``), scored against the run's truth
    (``result.truth``, else what the drones observed). The drones' sightings are those that
    count (:func:`run_sensing`), of the variance their :class:`SightingModel` gives, or
    ``meas_var`` when given. ``spatial`` adds the model ``nowcast-spatial``: the nowcast with
    the 4-neighbour coupling ``history.neighbour_corr``. When the run read fixed detectors
    (``result.extra["detectors"]``), the detectors-only reference row (swarm ``(detectors
    only)``, model ``nowcast``) and a ``nowcast+detectors`` row per swarm are added."""
    settings = settings or MonitorSettings()
    observed = result.importance
    if observed is None:
        raise ValueError("belief models need the run's importance maps (keep_importance=True)")
    truth = observed if result.truth is None else result.truth
    grid = result.grid
    steps = result.positions.shape[1]
    observed, truth = observed[:steps], truth[:steps]
    sighting, recorded = run_sensing(result)
    sensing = {"sighting": sighting, "recorded": recorded}
    events = congestion_events(truth, grid, settings.threshold, settings.min_duration)
    rows = []
    mean, std = history_belief(history, steps)
    rows.append(
        {"swarm": NO_DRONES, "model": "history"}
        | belief_scores(mean, std, truth, grid, settings, step_s, events)
    )
    detectors = (getattr(result, "extra", None) or {}).get("detectors")
    if detectors is not None:
        nobody = np.zeros((steps, 0, 2), dtype=np.int64)
        mean, std = nowcast(grid, nobody, observed, history, meas_var, 0.0, detectors,
                            detector_var)  # fmt: skip
        rows.append(
            {"swarm": DETECTORS_ONLY, "model": "nowcast"}
            | belief_scores(mean, std, truth, grid, settings, step_s, events)
        )
    for s, swarm in enumerate(result.swarms):
        positions = result.positions[s]
        couplings = [("nowcast", 0.0)] + (
            [("nowcast-spatial", history.neighbour_corr)] if spatial else []
        )
        models = [("last-seen", last_seen(grid, positions, observed, recorded))] + [
            (name, nowcast(grid, positions, observed, history, meas_var, c, **sensing))
            for name, c in couplings
        ]
        if detectors is not None:
            with_detectors = {"detectors": detectors, "detector_var": detector_var, **sensing}
            fused = nowcast(grid, positions, observed, history, meas_var, **with_detectors)
            models.append(("nowcast+detectors", fused))
        for model, (mean, std) in models:
            rows.append(
                {"swarm": swarm, "model": model}
                | belief_scores(mean, std, truth, grid, settings, step_s, events)
            )
    return pd.DataFrame(rows).assign(seed=result.seed)[["seed", "swarm", "model", *BELIEF_COLUMNS]]


def summarize(per_seed: pd.DataFrame) -> pd.DataFrame:
    """Mean over seeds per swarm and model (order kept), with ``n_seeds``."""
    grouped = per_seed.groupby(["swarm", "model"], sort=False)
    table = grouped[list(BELIEF_COLUMNS)].mean().reset_index()
    table["n_seeds"] = grouped.size().to_numpy()
    return table


def format_belief_table(table: pd.DataFrame, title: str = "Belief models") -> str:
    """The table as aligned text: error, calibration, % events known, latency, false alarms."""
    lines = [
        title,
        f"{'swarm':<22} {'model':<17} {'error':>7} {'calib90':>8} {'known %':>8} "
        f"{'lat med':>8} {'FA/h':>7}",
    ]

    def num(v, fmt):
        return "-" if pd.isna(v) else format(v, fmt)

    for r in table.itertuples(index=False):
        lat = r.latency_median_min if not pd.isna(r.latency_median_min) else r.latency_median_steps
        lines.append(
            f"{r.swarm:<22} {r.model:<17} {num(r.belief_error, '.4f'):>7} "
            f"{num(r.calibration_90, '.3f'):>8} {num(r.pct_events_known, '.1f'):>8} "
            f"{num(lat, '.1f'):>8} {num(r.false_alarms_per_hour, '.1f'):>7}"
        )
    unit = "min" if table["latency_median_min"].notna().any() else "steps"
    lines.append(
        f"error: importance-weighted MAE; calib90: share of true values inside the 90% "
        f"interval; known: congestion events with belief >= threshold while they last; "
        f"lat med: median latency ({unit}); FA/h: false-alarm onsets per hour"
    )
    return "\n".join(lines)


def check_source(history: History, where: Path | str, source) -> None:
    """:meth:`History.check_matches` against a traffic source about to run: its grid and
    horizon, and the step length, start and traffic seed of its metadata (a live run's, or
    those a tape recorded)."""
    meta = source.metadata() or {}
    meta = meta.get("recorded") or meta if meta.get("kind") == "tape" else meta
    step_s, begin, seed = meta.get("step_s"), meta.get("begin"), meta.get("seed")
    if meta.get("kind") in ("synthetic", "dynamic") and (history.step_s or history.begin):
        raise UserError(
            f"{where}: a history of SUMO days (from {history.begin or 'an unknown time'}) for "
            f"{meta['kind']} traffic, which has no clock; give a history of the same traffic "
            "(`twin history --dynamics` for generated days)"
        )
    clocked = meta.get("kind") not in ("synthetic", "dynamic")
    if clocked and not (history.step_s or history.begin):
        raise UserError(
            f"{where}: a history of generated days (no clock: `twin history --dynamics`) for "
            f"{meta.get('kind', 'SUMO')} traffic of a SUMO network; give a history of its days "
            "(`twin history --from` run folders of the same scenario)"
        )
    history.check_matches(
        where,
        source.grid.obstacles,
        int(source.horizon),
        float(step_s) if isinstance(step_s, (int, float)) else None,
        begin if isinstance(begin, str) else None,
        [seed] if isinstance(seed, int) and not isinstance(seed, bool) else [],
    )


def snapshot_steps(truth: np.ndarray, grid: Grid) -> list[int]:
    """Steps worth a look at the believed map: the peak of the mean true importance over the
    free cells (k >= 1), and half-way from the start to it and from it to the end."""
    horizon = truth.shape[0] - 1
    if horizon < 1:
        return [0]
    level = truth[1:, grid.free].mean(axis=1) if grid.free.any() else np.zeros(horizon)
    peak = 1 + int(np.argmax(level))
    return sorted({max(1, (1 + peak) // 2), peak, (peak + horizon + 1) // 2})


def belief_maps(
    result,
    history: History,
    settings: MonitorSettings | None = None,
    meas_var: float | None = None,
) -> dict[str, np.ndarray]:
    """What the report draws of one seed's nowcast (``belief_maps.npz``): the true map and
    every swarm's nowcast mean and std at :func:`snapshot_steps`, and for each congestion event
    the first step at which the history alone and each swarm's nowcast knew it (belief >=
    threshold while it lasts; -1: never), as :func:`belief_scores` counts them."""
    settings = settings or MonitorSettings()
    observed = result.importance
    if observed is None:
        raise ValueError("belief maps need the run's importance maps (keep_importance=True)")
    grid = result.grid
    steps = result.positions.shape[1]
    truth = np.asarray((observed if result.truth is None else result.truth)[:steps])
    observed = observed[:steps]
    events = congestion_events(truth, grid, settings.threshold, settings.min_duration)
    cell = events["i"].to_numpy(np.int64) * grid.ny + events["j"].to_numpy(np.int64)
    onset = events["onset"].to_numpy(np.int64)
    duration = events["duration"].to_numpy(np.int64)
    sighting, recorded = run_sensing(result)

    def known_at(mean: np.ndarray) -> np.ndarray:
        hot = mean >= settings.threshold
        out = np.full(len(cell), -1, dtype=np.int64)
        for e, (c, a, n) in enumerate(zip(cell, onset, duration, strict=True)):
            hit = np.flatnonzero(hot[a : a + n, c])
            if len(hit):
                out[e] = a + int(hit[0])
        return out

    at = np.array(snapshot_steps(truth, grid), dtype=np.int64)
    shape = (len(result.swarms), len(at), *grid.shape)
    means, stds = np.zeros(shape, np.float32), np.zeros(shape, np.float32)
    known = np.zeros((len(result.swarms), len(cell)), dtype=np.int64)
    for s in range(len(result.swarms)):
        mean, std = nowcast(grid, result.positions[s], observed, history, meas_var,
                            sighting=sighting, recorded=recorded)  # fmt: skip
        means[s] = mean[at].reshape(len(at), *grid.shape)
        stds[s] = std[at].reshape(len(at), *grid.shape)
        known[s] = known_at(mean)
    return {
        "seed": np.array(result.seed),
        "swarms": np.array(json.dumps(list(result.swarms))),
        "steps": at,
        "truth": truth[at].astype(np.float32),
        "mean": means,
        "std": stds,
        "threshold": np.array(settings.threshold),
        "event_i": events["i"].to_numpy(np.int64),
        "event_j": events["j"].to_numpy(np.int64),
        "event_onset": onset,
        "event_duration": duration,
        "known_at": known,
        "history_known_at": known_at(history_belief(history, steps)[0]),
    }


def run_beliefs(results, history: History, step_s: float | None) -> pd.DataFrame:
    """The belief-model table of a run (``belief_models.csv``): :func:`belief_table` of every
    seed's result, mean over seeds (:func:`summarize`)."""
    return summarize(
        pd.concat([belief_table(r, history, step_s=step_s) for r in results], ignore_index=True)
    )
