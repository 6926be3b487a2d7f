"""The observation model of the Shenzhen case study (Sec. IV-B): count -> density -> speed via a
Macroscopic Fundamental Diagram (MFD) -> importance (Def. 2).

Samples. At every sample time the twin reads, for every cell, the number of vehicles ``N`` and
their mean speed. With Edie's generalised definitions over a region of the cell's lanes (length
``L`` lane-km) and an instant ``dt``: total time spent ``N dt``, total distance ``sum(v_i) dt``,
so density ``k = N / L`` (veh per lane-km) and space-mean speed ``v = mean(v_i)``.

Form. Underwood's exponential speed-density relation, relative to each cell's speed limit:

    v(k) = a * v_lim * exp(-k / k_c)

Why this one: city cells rarely reach jam density, so Greenshields' linear form (speed zero at a
jam density) has a parameter the data hardly identify, and its straight line misses the convex
drop seen in urban speed-density scatter (fast early drop at signals and turns, long tail);
Underwood's form is convex, never negative, and has two well-identified parameters: ``a`` the
free-flow share of the limit (signals keep it below 1) and ``k_c`` the density at which speed
falls to ``1/e`` of free flow. Scaling by ``v_lim`` lets one fit serve cells with 40 km/h
streets and 90 km/h expressways.

Fit. Weighted least squares of the speed ratio ``v / v_lim`` on density, on samples pooled into
density bins (bin means weighted by the number of vehicles behind them), so the fit can be
updated online at constant cost: :class:`OnlineMFD` keeps the bins' running sums. The bins start
with pseudo-samples on a prior curve worth 1000 vehicles (a typical signalised grid, a = 0.7,
k_c = 40), because the first snapshots of a morning hold only low densities, which leave k_c
unidentified; by the end of a rush hour the data outweigh them a few hundred times.

Reads over the step. With ``reads`` instants per step, a cell's count is the total of
vehicle-instants over them and its speed their mean: Edie's definitions over the interval
(time spent ``sum N dt``, distance ``sum v_i dt``), so ``k = count / (reads L)``.

Thin data. A fit with fewer than ``MIN_FIT_SAMPLES`` cell samples, fewer than
``MIN_FIT_BINS`` occupied density bins, or a vehicle-weighted R^2 of the speed ratio below zero
on the data so far is not used: the model keeps the prior and says so (``used``, ``why``).

Importance. A drone's count ``N`` (optionally thinned by a detection model) gives ``k = N / L``,
the expected speed ``v(k)``, and the speed drop below the limit ``z = 1 - v(k) / v_lim``;
Def. 2 normalises it between an empty cell (``z_lo = 1 - a``) and standstill (``z_hi = 1``),
which gives ``T = 1 - exp(-k / k_c)`` on free cells.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.optimize import curve_fit

FORM = "underwood: v(k) = a * v_lim * exp(-k / k_c)"
#: Parameters used before any sample is in (a typical signalised city grid).
PRIOR_A, PRIOR_K_C = 0.7, 40.0
#: Weight (in vehicles) of the prior's pseudo-samples, spread over 0..PRIOR_MAX_DENSITY.
PRIOR_WEIGHT, PRIOR_MAX_DENSITY = 1000.0, 80.0
#: The ranges a configured MFD (``[traffic.mfd]``) and a tape's recorded one lie in: a
#: free-flow share ``a`` under 1% or a critical density ``k_c`` outside 1-1000 veh/lane-km (1000:
#: a car every metre) makes every cell empty or jammed, and a drone that sees under 1 vehicle in
#: 100 (``detection_p``) sees nothing.
SETTING_RANGES = {"a": (0.01, 1.0), "k_c": (1.0, 1000.0), "detection_p": (0.01, 1.0)}
#: Bounds that keep an early, thin fit sane.
A_BOUNDS, K_C_BOUNDS = (0.05, 1.5), (2.0, 1000.0)
#: A fit is used only on at least this many (cell, snapshot) samples with vehicles ...
MIN_FIT_SAMPLES = 200
#: ... spread over at least this many 1 veh/lane-km density bins ...
MIN_FIT_BINS = 10
#: ... and with a vehicle-weighted R^2 of the speed ratio on the data of at least this.
MIN_FIT_R2 = 0.0


@dataclass(frozen=True)
class MFD:
    """Underwood speed-density relation relative to the speed limit."""

    a: float = PRIOR_A
    k_c: float = PRIOR_K_C

    def speed_ratio(self, density: np.ndarray) -> np.ndarray:
        """Expected ``v / v_lim`` at density ``k`` (veh per lane-km)."""
        return self.a * np.exp(-np.asarray(density, dtype=float) / self.k_c)

    def speed(self, density: np.ndarray, speed_limit: np.ndarray) -> np.ndarray:
        """Expected space-mean speed (m/s)."""
        return self.speed_ratio(density) * np.asarray(speed_limit, dtype=float)

    def importance(self, density: np.ndarray) -> np.ndarray:
        """Def. 2 on the speed drop ``z = 1 - v / v_lim`` with ``z_lo = 1 - a``, ``z_hi = 1``."""
        z = 1.0 - self.speed_ratio(density)
        z_lo, z_hi = 1.0 - self.a, 1.0
        return np.clip((z - z_lo) / (z_hi - z_lo), 0.0, 1.0)

    def to_json(self) -> dict:
        return {"form": FORM, **asdict(self)}


def _underwood(k: np.ndarray, a: float, k_c: float) -> np.ndarray:
    return a * np.exp(-k / k_c)


def fit_underwood(
    density: np.ndarray, ratio: np.ndarray, weight: np.ndarray, prior: MFD = MFD()
) -> MFD:
    """Weighted least squares of ``ratio ~ a exp(-density / k_c)``; ``prior`` when too thin."""
    density, ratio, weight = (np.asarray(x, dtype=float) for x in (density, ratio, weight))
    ok = (weight > 0) & np.isfinite(ratio) & np.isfinite(density)
    if ok.sum() < 3 or np.ptp(density[ok]) <= 0:
        return prior
    try:
        (a, k_c), _ = curve_fit(
            _underwood,
            density[ok],
            ratio[ok],
            p0=(prior.a, prior.k_c),
            sigma=1.0 / np.sqrt(weight[ok]),
            bounds=([A_BOUNDS[0], K_C_BOUNDS[0]], [A_BOUNDS[1], K_C_BOUNDS[1]]),
            maxfev=2000,
        )
    except (RuntimeError, ValueError):
        return prior
    return MFD(float(a), float(k_c))


class OnlineMFD:
    """Running density-binned sums of (density, speed ratio) samples and the fit on them.

    :meth:`add` takes one snapshot of every cell; :meth:`fit` refits on everything added so far.
    Cells without vehicles carry no speed and are left out.
    """

    def __init__(
        self,
        bin_width: float = 1.0,
        max_density: float = 300.0,
        prior: MFD = MFD(),
        prior_weight: float = PRIOR_WEIGHT,
    ):
        self.bin_width = bin_width
        self.n_bins = int(np.ceil(max_density / bin_width)) + 1
        self.prior = prior
        self.weight = np.zeros(self.n_bins)  # vehicles behind each bin
        self.k_sum = np.zeros(self.n_bins)  # vehicle-weighted sums of density
        self.r_sum = np.zeros(self.n_bins)  # vehicle-weighted sums of speed ratio
        # The data alone (no pseudo-samples): weights, sums of ratio and of squared ratio.
        self.data_w = np.zeros(self.n_bins)
        self.data_k = np.zeros(self.n_bins)
        self.data_r = np.zeros(self.n_bins)
        self.data_rr = np.zeros(self.n_bins)
        self.n_samples = 0
        if prior_weight > 0:
            # Pseudo-samples on the prior curve: early snapshots hold only low densities, which
            # say nothing about k_c; the prior holds the curve there until data comes in.
            k = np.arange(0.0, PRIOR_MAX_DENSITY + 1e-9, 2.0)
            self.add_weighted(np.full(len(k), prior_weight / len(k)), k, prior.speed_ratio(k))

    def add(self, count: np.ndarray, density: np.ndarray, ratio: np.ndarray) -> None:
        """One snapshot: cells with vehicles count, weighted by their number of vehicles."""
        ok = (count > 0) & np.isfinite(ratio) & np.isfinite(density)
        w, k, r = count[ok].astype(float), density[ok], ratio[ok]
        self.add_weighted(w, k, r)
        b = self._bins(k)
        for total, x in ((self.data_w, w), (self.data_k, w * k), (self.data_r, w * r)):
            total += np.bincount(b, weights=x, minlength=self.n_bins)
        self.data_rr += np.bincount(b, weights=w * r * r, minlength=self.n_bins)
        self.n_samples += int(ok.sum())

    def _bins(self, density: np.ndarray) -> np.ndarray:
        return np.minimum((density / self.bin_width).astype(np.int64), self.n_bins - 1)

    def add_weighted(self, w: np.ndarray, density: np.ndarray, ratio: np.ndarray) -> None:
        b = self._bins(density)
        self.weight += np.bincount(b, weights=w, minlength=self.n_bins)
        self.k_sum += np.bincount(b, weights=w * density, minlength=self.n_bins)
        self.r_sum += np.bincount(b, weights=w * ratio, minlength=self.n_bins)

    def fit(self) -> MFD:
        if self.n_samples == 0:
            return self.prior
        used = self.weight > 0
        w = self.weight[used]
        return fit_underwood(self.k_sum[used] / w, self.r_sum[used] / w, w, self.prior)

    def data_r2(self, mfd: MFD) -> float:
        """Vehicle-weighted R^2 of ``mfd``'s speed ratio on the data added so far (no prior),
        from the bin sums: each sample is compared with the curve at its bin's mean density."""
        used = self.data_w > 0
        if not used.any():
            return float("nan")
        w, r, r2 = self.data_w[used], self.data_r[used], self.data_rr[used]
        f = mfd.speed_ratio(self.data_k[used] / w)
        ss_tot = float(r2.sum() - r.sum() ** 2 / w.sum())
        ss_res = float((r2 - 2 * f * r + f * f * w).sum())
        return 1.0 - ss_res / ss_tot if ss_tot > 1e-12 else float("nan")

    def choose(self) -> tuple[MFD, str, str]:
        """The MFD to use now: the fit, or the prior when the data are too thin or the fit
        explains them worse than their mean (``(mfd, "fit" | "prior", why)``)."""
        bins = int((self.data_w > 0).sum())
        if self.n_samples < MIN_FIT_SAMPLES or bins < MIN_FIT_BINS:
            why = (
                f"{self.n_samples} samples over {bins} density bins "
                f"(a fit needs {MIN_FIT_SAMPLES} over {MIN_FIT_BINS})"
            )
            return self.prior, "prior", why
        fit = self.fit()
        r2 = self.data_r2(fit)
        if not r2 >= MIN_FIT_R2:  # also NaN: data without spread
            return self.prior, "prior", f"fit R2 = {r2:.3f} on the data, below {MIN_FIT_R2:g}"
        return fit, "fit", f"{self.n_samples} samples, fit R2 = {r2:.3f} on the data"


def fit_quality(mfd: MFD, density, speed, speed_limit) -> dict[str, float]:
    """R^2 and RMSE (km/h) of the MFD's speed against ground-truth cell speeds."""
    density, speed, speed_limit = (
        np.asarray(x, dtype=float) for x in (density, speed, speed_limit)
    )
    ok = np.isfinite(speed) & np.isfinite(density) & (speed_limit > 0)
    if not ok.any():
        return {"r2": float("nan"), "rmse_kmh": float("nan"), "n": 0}
    pred = mfd.speed(density[ok], speed_limit[ok])
    resid = speed[ok] - pred
    ss_tot = float(((speed[ok] - speed[ok].mean()) ** 2).sum())
    r2 = 1.0 - float((resid**2).sum()) / ss_tot if ss_tot > 0 else float("nan")
    return {"r2": r2, "rmse_kmh": float(np.sqrt((resid**2).mean()) * 3.6), "n": int(ok.sum())}


def detected_counts(count: np.ndarray, p: float, rng: np.random.Generator) -> np.ndarray:
    """Imperfect vision: each vehicle is seen with probability ``p`` (binomial thinning)."""
    if p >= 1.0:
        return np.asarray(count)
    return rng.binomial(np.asarray(count, dtype=np.int64), p)


#: Effective vehicle length (m) in ``density = occupancy / length`` of a fixed detector
#: (:mod:`twin.sumo.detectors`): SUMO's default passenger car (5 m) seen by a point loop.
VEHICLE_LENGTH_M = 5.0


def density_from_occupancy(occupancy_pct: np.ndarray) -> np.ndarray:
    """Vehicles per lane-km from a detector's occupancy (%): ``k = occ / L``."""
    return np.asarray(occupancy_pct, dtype=float) / 100.0 * 1000.0 / VEHICLE_LENGTH_M


def density_from_counts(count: np.ndarray, lane_km: np.ndarray, p: float = 1.0) -> np.ndarray:
    """Vehicles per lane-km; a count seen with probability ``p`` is scaled by ``1/p``."""
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(
            lane_km > 0, np.asarray(count, float) / (p * np.maximum(lane_km, 1e-12)), 0.0
        )


#: The columns of the MFD's samples (``mfd_samples.parquet``), with their types when empty.
EMPTY_SAMPLE_COLUMNS = {
    "step": np.int64, "i": np.int64, "j": np.int64, "count": np.int64, "lane_km": np.float64,
    "density": np.float64, "speed": np.float64, "speed_limit": np.float64,
    "speed_mfd_online": np.float64,
}  # fmt: skip


class MFDImportance:
    """Snapshot by snapshot, per-cell counts and ground-truth speeds -> importance ``T^k``.

    One home for the observation model, used by the live SUMO source and by the tape replay, so
    that both give the same maps. Each snapshot is first observed with the MFD fitted on the
    snapshots before it (online and causal: no look-ahead), then added to the fit. With
    ``fit="fixed"`` the given MFD is used throughout. ``detection_p < 1`` thins the counts the
    drones see (seeded), the fit always uses the simulation's ground truth.
    """

    def __init__(
        self,
        free: np.ndarray,
        lane_km: np.ndarray,
        speed_limit: np.ndarray,
        fit: str = "online",
        mfd: MFD = MFD(),
        detection_p: float = 1.0,
        seed: int = 0,
        reads: int = 1,
    ):
        if reads < 1:
            raise ValueError(f"reads per step must be >= 1, got {reads}")
        if fit not in ("online", "fixed"):
            raise ValueError(f"fit must be 'online' or 'fixed', got {fit!r}")
        if not 0.0 < detection_p <= 1.0:
            raise ValueError(f"detection probability must lie in (0, 1], got {detection_p}")
        self.free = np.asarray(free, dtype=bool)
        self.lane_km = np.asarray(lane_km, dtype=float)
        self.speed_limit = np.asarray(speed_limit, dtype=float)
        self.fit_mode = fit
        self.mfd = mfd
        self.detection_p = detection_p
        self.seed = seed
        self.rng = np.random.default_rng([seed, 0x6D6664])
        self.reads = int(reads)
        self.online = OnlineMFD(prior=mfd)
        self.used, self.why = (
            "prior",
            ('fit = "fixed": the given MFD' if fit == "fixed" else "no data yet"),
        )
        self._samples: list[dict[str, np.ndarray]] = []
        #: snapshots observed so far (a run stopped early may keep fewer: :meth:`observe`)
        self.observed = 0

    def observe(self, step: int, count: np.ndarray, speed: np.ndarray) -> np.ndarray:
        """``T`` of one snapshot (Def. 2), then learn from the snapshot's ground truth.

        ``count`` is the vehicle-instants of each cell over the step's ``reads`` instants and
        ``speed`` their mean (the count itself with one read)."""
        self.observed += 1
        total = np.asarray(count)
        seen = detected_counts(total, self.detection_p, self.rng)
        r = self.reads
        importance = np.where(
            self.free,
            self.mfd.importance(density_from_counts(seen, self.lane_km, self.detection_p * r)),
            0.0,
        )
        count = total / r if r > 1 else total  # mean vehicles in the cell over the step
        density = density_from_counts(total, self.lane_km, float(r))
        # the truth: the same model on every vehicle (what drones see, unless some are missed)
        self.truth = (
            importance if self.detection_p >= 1.0
            else np.where(self.free, self.mfd.importance(density), 0.0)
        )  # fmt: skip
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = np.where(
                self.speed_limit > 0, speed / np.maximum(self.speed_limit, 1e-9), np.nan
            )
        sampled = self.free & (count > 0)
        i, j = np.nonzero(sampled)
        self._samples.append(
            {
                "step": np.full(len(i), step, dtype=np.int64),
                "i": i,
                "j": j,
                "count": count[sampled] if r > 1 else count[sampled].astype(np.int64),
                "lane_km": self.lane_km[sampled],
                "density": density[sampled],
                "speed": speed[sampled],
                "speed_limit": self.speed_limit[sampled],
                "speed_mfd_online": self.mfd.speed(density[sampled], self.speed_limit[sampled]),
            }
        )
        self.online.add(np.where(self.free, count, 0), density, ratio)
        if self.fit_mode == "online":
            self.mfd, self.used, self.why = self.online.choose()
        return importance

    def binned_r2(self) -> float:
        """R^2 of the fitted curve against the vehicle-weighted mean speed ratio of each
        1 veh/lane-km density bin: how well the form captures the mean relation, apart from
        the scatter of single cells (a car waiting at a red light has speed 0)."""
        o = self.online
        used = o.weight > 0
        if used.sum() < 2:
            return float("nan")
        w = o.weight[used]
        k, r = o.k_sum[used] / w, o.r_sum[used] / w
        mean = float((w * r).sum() / w.sum())
        ss_tot = float((w * (r - mean) ** 2).sum())
        ss_res = float((w * (r - self.mfd.speed_ratio(k)) ** 2).sum())
        return 1.0 - ss_res / ss_tot if ss_tot > 0 else float("nan")

    def samples(self) -> dict[str, np.ndarray]:
        """Every (cell, snapshot) sample with vehicles: the MFD's data (``mfd_samples``)."""
        if not self._samples:  # the same columns, empty: a run folder's file keeps its shape
            return {k: np.empty(0, dtype) for k, dtype in EMPTY_SAMPLE_COLUMNS.items()}
        keys = self._samples[0].keys()
        return {k: np.concatenate([s[k] for s in self._samples]) for k in keys}

    def report(self) -> dict:
        """The final fit and its quality against SUMO's ground truth (``mfd.json``)."""
        s = self.samples()
        used = {"used": self.used, "why": self.why, "reads_per_step": self.reads}
        if self.fit_mode == "online" and self.used == "prior" and self.online.n_samples:
            fit = self.online.fit()
            used["rejected_fit"] = {"a": fit.a, "k_c": fit.k_c}
        if not len(s["step"]):
            return {**self.mfd.to_json(), "fit": self.fit_mode, **used, "n_samples": 0}
        final = fit_quality(self.mfd, s["density"], s["speed"], s["speed_limit"])
        online = {"r2": float("nan"), "rmse_kmh": float("nan")}
        ok = np.isfinite(s["speed"])
        if ok.any():
            resid = s["speed"][ok] - s["speed_mfd_online"][ok]
            ss_tot = float(((s["speed"][ok] - s["speed"][ok].mean()) ** 2).sum())
            online = {
                "r2": 1.0 - float((resid**2).sum()) / ss_tot if ss_tot > 0 else float("nan"),
                "rmse_kmh": float(np.sqrt((resid**2).mean()) * 3.6),
            }
        return {
            **self.mfd.to_json(),
            "fit": self.fit_mode,
            **used,
            "detection_p": self.detection_p,
            "r2_binned": self.binned_r2(),
            "density_unit": "veh per lane-km",
            "speed_unit": "m/s",
            "n_samples": final["n"],
            "r2": final["r2"],
            "rmse_kmh": final["rmse_kmh"],
            "online_r2": online["r2"],
            "online_rmse_kmh": online["rmse_kmh"],
            "importance": "T = clip((z - (1 - a)) / a, 0, 1), z = 1 - v(k) / v_lim",
        }
