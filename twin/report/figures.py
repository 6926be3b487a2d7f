"""The report's figures, each drawn from a :class:`~twin.report.load.RunFiles` onto a fresh
matplotlib :class:`~matplotlib.figure.Figure` (Agg canvas; pyplot's global state is never used).

Cell ``(i, j)`` is drawn at ``x = j``, ``y = i`` with row 0 at the top, as in the paper's maps.
"""

from __future__ import annotations

import gzip
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from matplotlib import colormaps
from matplotlib.axes import Axes
from matplotlib.collections import LineCollection
from matplotlib.colors import ListedColormap, to_rgb
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from twin.report.load import RunFiles
from twin.report.stats import mean_band

#: Paper's Fig. 4 snapshot steps.
SNAPSHOT_STEPS = (0, 40, 90, 140)
#: Drone markers, after the paper's swarm D = {triangle, square, circle, star}.
DRONE_MARKERS = ("^", "s", "o", "*", "D", "v", "P", "X")
IMPORTANCE_CMAP = "inferno"
OBSTACLE_COLOUR = "#b8b8b8"


def swarm_colours(swarms: list[str]) -> dict[str, Any]:
    cmap = colormaps["tab10"]
    return {name: cmap(k % 10) for k, name in enumerate(swarms)}


def drone_colours(n: int) -> list[Any]:
    cmap = colormaps["Set2" if n <= 8 else "tab20"]
    return [cmap(d % cmap.N) for d in range(n)]


def _cmap_with_obstacles(name: str) -> ListedColormap:
    return colormaps[name].with_extremes(bad=OBSTACLE_COLOUR)


def importance_label(rf: RunFiles) -> str:
    """Colour-bar label of importance maps, saying where the scale stops."""
    vmax = rf.importance_vmax
    if vmax >= 1.0:
        return "importance $T^k$ (1 = most congested)"
    return f"importance $T^k$ (scale up to the run's peak, {vmax:g})"


def snapshot_steps(horizon: int, wanted: tuple[int, ...] = SNAPSHOT_STEPS) -> list[int]:
    """The paper's snapshot steps clipped to the horizon (duplicates dropped)."""
    return sorted({min(k, horizon) for k in wanted})


def panel_layout(n: int) -> tuple[int, int]:
    """Rows, columns for ``n`` map panels (2 x 2 for four swarms)."""
    if n <= 3:
        return 1, n
    cols = int(np.ceil(np.sqrt(n)))
    return int(np.ceil(n / cols)), cols


def draw_map(ax: Axes, values: np.ndarray, obstacles: np.ndarray, cmap: str, vmax: float = 1.0):
    """A cell map with obstacles greyed out; returns the image for a colour bar."""
    masked = np.ma.masked_array(values, mask=obstacles)
    image = ax.imshow(
        masked,
        cmap=_cmap_with_obstacles(cmap),
        vmin=0.0,
        vmax=vmax,
        origin="upper",
        interpolation="nearest",
        aspect="equal",
    )
    ax.set_xlim(-0.5, values.shape[1] - 0.5)
    ax.set_ylim(values.shape[0] - 0.5, -0.5)
    ax.set_xlabel("column j", fontsize=8)
    ax.set_ylabel("row i", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.yaxis.set_major_locator(MaxNLocator(integer=True))
    return image


def draw_drones(ax: Axes, positions: np.ndarray, k: int, trail: int, colours: list[Any]) -> None:
    """Each drone's path over steps ``max(0, k - trail) .. k`` and its marker at ``P_k``.

    One line collection for the paths and one scatter per marker shape, so that 200 drones
    cost a handful of artists, not 400."""
    start = max(0, k - trail)
    path = positions[start : k + 1]  # (L, N, 2)
    n = positions.shape[1]
    segments = np.transpose(path[:, :, ::-1], (1, 0, 2)).astype(float)  # (N, L, 2) as (x, y)
    ax.add_collection(
        LineCollection(segments, colors=colours, linewidths=1.4, alpha=0.85), autolim=False
    )
    at = positions[k]
    rgba = np.asarray(colours, dtype=float).reshape(n, -1)
    size = 64.0 if n <= 16 else max(6.0, 64.0 * 16 / n)  # hundreds of drones: small marks
    for m, marker in enumerate(DRONE_MARKERS):
        d = np.arange(m, n, len(DRONE_MARKERS))
        if len(d) == 0:
            continue
        ax.scatter(
            at[d, 1],
            at[d, 0],
            marker=marker,
            c=rgba[d],
            edgecolors="white",
            s=size,
            linewidths=0.8 if n <= 16 else 0.3,
            zorder=3,
        )


def figure_scores(rf: RunFiles) -> Figure:
    """Fig. 3 analog: cumulative score, per-step score, share of map visited, coverage C^k."""
    panels = (
        ("cumulative_reward", "cumulative patrolling score $R^k$", 1.0),
        ("reward", "patrolling score per step (rolling mean)", 1.0),
        ("visited_share", "map visited (%)", 100.0),
        ("coverage", "coverage $C^k$", 1.0),
    )
    colours = swarm_colours(rf.swarms)
    n_seeds = len(rf.seeds)
    horizon = int(rf.series["step"].max()) + 1
    window = max(1, horizon // 40)
    fig = Figure(figsize=(11, 7), layout="constrained")
    axes = fig.subplots(2, 2, sharex=True).ravel()
    for ax, (column, label, scale) in zip(axes, panels, strict=True):
        for swarm, (steps, mean, half) in mean_band(rf.series, column).items():
            x = steps + 1  # value after the move of step k
            if column == "reward" and window > 1:
                mean, half = (
                    pd.Series(v).rolling(window, center=True, min_periods=1).mean().to_numpy()
                    for v in (mean, half)
                )
            ax.plot(x, scale * mean, color=colours.get(swarm), lw=1.5, label=swarm)
            if n_seeds > 1:
                ax.fill_between(
                    x,
                    scale * (mean - half),
                    scale * (mean + half),
                    color=colours.get(swarm),
                    alpha=0.2,
                )
        title = label if column != "reward" or window == 1 else f"{label}, window {window}"
        ax.set_title(title, fontsize=10)
        ax.set_ylabel(label.split(" (")[0], fontsize=9)
        ax.grid(alpha=0.3)
    for ax in axes[2:]:
        ax.set_xlabel("step k", fontsize=9)
    band = f"mean and 95% interval over {n_seeds} seeds" if n_seeds > 1 else f"seed {rf.seeds[0]}"
    axes[0].legend(fontsize=8, loc="upper left")
    fig.suptitle(f"Swarm performance over the horizon ({band})", fontsize=12)
    return fig


def figure_snapshots(rf: RunFiles, trail: int = 10) -> Figure:
    """Fig. 4 analog: importance ``T^k`` with each swarm's drones at the paper's steps."""
    steps = snapshot_steps(rf.horizon)
    swarms = rf.swarms
    # A fixed layout (no constrained layout: it doubles the drawing time of 16 panels) with
    # tick labels on the outer panels only.
    width, height = 3.0 * len(steps) + 1.2, 2.2 * len(swarms) + 0.9
    fig = Figure(figsize=(width, height))
    fig.subplots_adjust(
        left=0.6 / width, right=1 - 1.3 / width, bottom=0.55 / height, top=1 - 0.6 / height,
        wspace=0.08, hspace=0.3,
    )  # fmt: skip
    axes = fig.subplots(len(swarms), len(steps), squeeze=False, sharex=True, sharey=True)
    image = None
    for r, swarm in enumerate(swarms):
        positions = rf.positions(swarm)
        colours = drone_colours(positions.shape[1])
        for c, k in enumerate(steps):
            ax = axes[r, c]
            image = draw_map(
                ax, rf.importance[k], rf.obstacles, IMPORTANCE_CMAP, rf.importance_vmax
            )
            draw_drones(ax, positions, k, trail, colours)
            clock = rf.clock(k)
            ax.set_title(f"{swarm}, k = {k}" + (f" ({clock})" if clock else ""), fontsize=9)
            ax.label_outer()
    cax = fig.add_axes((1 - 1.05 / width, 0.15, 0.18 / width, 0.7))
    fig.colorbar(image, cax=cax, label=importance_label(rf))
    fig.suptitle(
        f"Drones over the importance map at k = {', '.join(map(str, steps))} "
        f"(seed {rf.first_seed}; lines: last {trail} steps)",
        fontsize=11,
    )
    return fig


def first_peak_step(rf: RunFiles, after: int) -> int:
    """The first step :func:`peak_step` looks at: ``after``, or the last of a shorter run."""
    return min(after, rf.horizon)


def peak_step(rf: RunFiles, after: int) -> int:
    """The step ``k >= after`` at which the mean importance over free cells is highest."""
    mean = rf.importance[:, ~rf.obstacles].mean(axis=1)
    start = first_peak_step(rf, after)
    return start + int(np.argmax(mean[start:]))


#: Steps of each swarm's path drawn on Fig. 2 (its step is chosen from this one on).
TRAIL_STEPS = 40


def figure_trajectories(rf: RunFiles, trail: int = TRAIL_STEPS) -> tuple[Figure, int]:
    """Fig. 2 analog: each swarm's last ``trail`` steps over ``I^k T^k`` at the step of peak
    congestion (highest mean importance, at least ``trail`` steps in); returns that step."""
    swarms = rf.swarms
    rows, cols = panel_layout(len(swarms))
    k = peak_step(rf, trail)
    fig = Figure(figsize=(4.2 * cols + 1.0, 3.1 * rows + 0.8), layout="constrained")
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    image = None
    for ax, swarm in zip(axes, swarms, strict=False):
        positions = rf.positions(swarm)
        kk = min(k, len(positions) - 1)
        weighted = rf.idleness(swarm)[kk] * rf.importance[kk]
        image = draw_map(ax, weighted, rf.obstacles, "magma", rf.importance_vmax)
        draw_drones(ax, positions, kk, trail, drone_colours(positions.shape[1]))
        ax.set_title(swarm, fontsize=10)
    for ax in axes[len(swarms) :]:
        ax.set_visible(False)
    fig.colorbar(image, ax=axes.tolist(), shrink=0.8, label="$I^k T^k$ (unvisited importance)")
    clock = rf.clock(k)
    fig.suptitle(
        f"Trajectories of the last {min(trail, k)} steps over $I^k T^k$ at k = {k}"
        + (f" ({clock})" if clock else "")
        + f", the step of highest mean importance (seed {rf.first_seed})",
        fontsize=11,
    )
    return fig, k


def figure_traffic(rf: RunFiles) -> Figure:
    """How congestion forms: importance over the horizon, and the simulated vehicles and speeds
    (from mfd_samples.parquet) when the run has them."""
    free = ~rf.obstacles
    values = rf.importance[:, free]  # (T+1, n_free)
    steps = np.arange(len(values))
    samples = rf.mfd_samples
    has_sim = samples is not None and {"step", "speed", "count"} <= set(samples.columns)
    fig = Figure(figsize=(11, 6.4 if has_sim else 3.4), layout="constrained")
    axes = fig.subplots(2 if has_sim else 1, 2, squeeze=False).ravel()
    ax = axes[0]
    ax.plot(steps, values.mean(axis=1), label="mean over free cells")
    ax.plot(steps, np.percentile(values, 90, axis=1), label="90th percentile")
    ax.plot(steps, values.max(axis=1), label="maximum", lw=0.8)
    ax.set_title("importance $T^k$ over time", fontsize=10)
    ax.set_ylabel("importance")
    ax.legend(fontsize=8)
    ax = axes[1]
    for share in (0.25, 0.5, 0.75):
        level = round(share * rf.importance_vmax, 3)
        ax.plot(steps, 100.0 * (values >= level).mean(axis=1), label=f"$T^k \\geq$ {level:g}")
    ax.set_title("share of free cells above an importance level", fontsize=10)
    ax.set_ylabel("% of free cells")
    ax.legend(fontsize=8)
    if has_sim:
        per_step = samples.assign(moving=samples["speed"].fillna(0.0) * samples["count"]).groupby(
            "step"
        )
        vehicles = per_step["count"].sum()
        ax = axes[2]
        ax.plot(vehicles.index, vehicles.to_numpy(), color="#444")
        ax.set_title("vehicles on the grid (simulation; k < 0: warm-up)", fontsize=10)
        ax.set_ylabel("vehicles")
        ax = axes[3]
        kmh = 3.6 if (rf.mfd or {}).get("speed_unit", "m/s") == "m/s" else 1.0
        mean_speed = kmh * per_step["moving"].sum() / vehicles.clip(lower=1)
        ax.plot(mean_speed.index, mean_speed.to_numpy(), color="#c0392b", lw=0.8, alpha=0.6,
                label="at each sample")  # fmt: skip
        smooth = mean_speed.rolling(8, center=True, min_periods=1).mean()
        ax.plot(
            smooth.index, smooth.to_numpy(), color="#7b241c", lw=2, label="rolling mean, 8 steps"
        )
        ax.legend(fontsize=8)
        ax.set_title("mean vehicle speed (simulation)", fontsize=10)
        ax.set_ylabel("km/h" if kmh != 1.0 else "speed")
    for ax in axes:
        ax.set_xlabel("step k" + _clock_note(rf))
        ax.grid(alpha=0.3)
    fig.suptitle(f"Traffic over the horizon (seed {rf.first_seed})", fontsize=11)
    return fig


#: Most events drawn in the events figure (the earliest onsets; the caption gives the count).
MAX_EVENTS_DRAWN = 60


def events_drawn(rf: RunFiles) -> tuple[pd.DataFrame, int]:
    """The first seed's events (one row per event) drawn in :func:`figure_events`, and how many
    the seed has."""
    ev = rf.events
    if ev is None or ev.empty:
        return pd.DataFrame(columns=["event", "i", "j", "onset", "duration", "peak"]), 0
    ev = ev[ev["seed"] == rf.first_seed]
    one = ev.drop_duplicates("event").sort_values(["onset", "i", "j"])
    return one.head(MAX_EVENTS_DRAWN), len(one)


def figure_events(rf: RunFiles) -> Figure:
    """Congestion events of the first seed as horizontal bars (cell, onset to end, shade =
    peak), with a marker where each swarm first saw each event; x for an event it missed."""
    drawn, total = events_drawn(rf)
    ev = rf.events[rf.events["seed"] == rf.first_seed] if rf.events is not None else None
    colours = swarm_colours(rf.swarms)
    n = max(len(drawn), 1)
    fig = Figure(figsize=(11, min(2.5 + 0.18 * n, 14)), layout="constrained")
    ax = fig.subplots()
    cmap = colormaps["Reds"]
    rows = {int(e): y for y, e in enumerate(drawn["event"])}
    for y, e in enumerate(drawn.itertuples(index=False)):
        ax.barh(y, e.duration, left=e.onset, height=0.7, color=cmap(0.3 + 0.7 * float(e.peak)),
                edgecolor="#7b241c", lw=0.4)  # fmt: skip
    n_swarms = max(len(rf.swarms), 1)
    for s, swarm in enumerate(rf.swarms):
        if ev is None or not rows:
            break
        mine = ev[(ev["swarm"] == swarm) & ev["event"].isin(rows)]
        y = mine["event"].map(rows).to_numpy() + (s - (n_swarms - 1) / 2) * 0.6 / n_swarms
        seen = mine["seen"].to_numpy(bool)
        end = (mine["onset"] + mine["duration"]).to_numpy()
        ax.plot(mine["first_seen"].to_numpy()[seen], y[seen], "o", color=colours[swarm], ms=4,
                label=f"{swarm}: first seen")  # fmt: skip
        ax.plot(end[~seen], y[~seen], "x", color=colours[swarm], ms=4, label=f"{swarm}: missed")
    ax.set_yticks(range(len(drawn)))
    ax.set_yticklabels([f"({e.i}, {e.j})" for e in drawn.itertuples(index=False)], fontsize=6)
    ax.invert_yaxis()
    ax.set_xlim(0, rf.horizon + 1)
    ax.set_xlabel("step k" + _clock_note(rf))
    ax.set_ylabel("cell (i, j) of the event")
    ax.grid(alpha=0.3, axis="x")
    if rows:
        ax.legend(fontsize=7, ncol=min(4, 2 * n_swarms), loc="lower right")
    shown = f"{len(drawn)} of {total}" if total > len(drawn) else f"{total}"
    threshold = (rf.run.get("monitoring") or {}).get("threshold")
    level = f", true importance >= {threshold:g}" if isinstance(threshold, (int, float)) else ""
    fig.suptitle(f"Congestion events (seed {rf.first_seed}, {shown} events{level})", fontsize=11)
    return fig


def figure_belief(rf: RunFiles) -> Figure:
    """Belief error of every swarm over the horizon (mean and 95% interval over seeds)."""
    colours = swarm_colours(rf.swarms)
    n_seeds = len(rf.seeds)
    fig = Figure(figsize=(11, 3.6), layout="constrained")
    ax = fig.subplots()
    for swarm, (steps, mean, half) in mean_band(rf.series, "belief_error").items():
        x = steps + 1  # after the drones' view from P_{k+1}
        ax.plot(x, mean, color=colours.get(swarm), lw=1.3, label=swarm)
        if n_seeds > 1:
            ax.fill_between(x, mean - half, mean + half, color=colours.get(swarm), alpha=0.2)
    ax.set_xlabel("step k" + _clock_note(rf))
    ax.set_ylabel("belief error")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    band = f"mean and 95% interval over {n_seeds} seeds" if n_seeds > 1 else f"seed {rf.seeds[0]}"
    fig.suptitle(f"Importance-weighted error of each swarm's believed map ({band})", fontsize=11)
    return fig


def _clock_note(rf: RunFiles) -> str:
    begin, step_s = rf.clock_start()
    return f" ({step_s:g} s each from {begin})" if begin else ""


def grid_geometry(network: dict[str, Any]) -> tuple[float, float, float, float]:
    """``(x_left, y_top, cell_width, cell_height)`` in network metres from network.json's
    ``grid`` (``x0`` western edge of column 0, ``y_top`` northern edge of row 0, ``cell_m``)."""
    grid = network["grid"]
    cell = float(grid["cell_m"])
    return float(grid["x0"]), float(grid["y_top"]), cell, cell


def read_lane_shapes(net_file: Path) -> list[np.ndarray]:
    """Shapes of the non-internal lanes of a SUMO ``.net.xml`` (or ``.net.xml.gz``)."""
    opener = gzip.open if net_file.suffix == ".gz" else open
    shapes: list[np.ndarray] = []
    internal = False
    with opener(net_file, "rb") as handle:
        for event, elem in ET.iterparse(handle, events=("start", "end")):
            if elem.tag == "edge":
                if event == "start":
                    internal = elem.get("function") == "internal"
                else:
                    elem.clear()
            elif elem.tag == "lane" and event == "end" and not internal:
                shape = elem.get("shape")
                if shape:
                    points = [tuple(map(float, p.split(",")[:2])) for p in shape.split()]
                    shapes.append(np.asarray(points))
    return shapes


def resolve_net_file(rf: RunFiles) -> Path | None:
    network = rf.network or {}
    name = network.get("net_file")
    if not name:
        return None
    for candidate in (Path(name), rf.run_dir / name, rf.run_dir / Path(name).name):
        if candidate.exists():
            return candidate
    return None


def figure_network(rf: RunFiles) -> tuple[Figure, str]:
    """The network's lanes with the monitoring grid and obstacle cells; returns a caption note."""
    nx, ny = rf.obstacles.shape
    peak = rf.importance.max(axis=0)
    fig = Figure(figsize=(10, 10 * nx / ny + 0.8), layout="constrained")
    ax = fig.subplots()
    note = ""
    net_file = resolve_net_file(rf) if rf.network else None
    geometry = None
    if rf.network is not None:
        try:
            geometry = grid_geometry(rf.network)
        except (KeyError, TypeError, IndexError) as exc:
            note = f"network.json: grid geometry unreadable ({exc}); grid drawn in cell units."
    if geometry is None:
        geometry = (-0.5, -0.5, 1.0, -1.0)  # cell units: x = j, y = i growing downwards
    x_left, y_top, cw, ch = geometry
    extent = (x_left, x_left + ny * cw, y_top - nx * ch, y_top)
    masked = np.ma.masked_array(peak, mask=rf.obstacles)
    image = ax.imshow(
        masked, cmap=IMPORTANCE_CMAP, vmin=0, vmax=rf.importance_vmax, alpha=0.55, extent=extent, origin="upper",
        interpolation="nearest",
    )  # fmt: skip
    # obstacle cells: one grey overlay and one hatched contour (not a patch per cell)
    grey = np.zeros((nx, ny, 4))
    grey[rf.obstacles] = (*to_rgb(OBSTACLE_COLOUR), 0.8)
    ax.imshow(grey, extent=extent, origin="upper", interpolation="nearest")
    if rf.obstacles.any():
        xs = x_left + (np.arange(ny) + 0.5) * cw
        ys = y_top - (np.arange(nx) + 0.5) * ch
        ax.contourf(
            xs, ys, rf.obstacles.astype(float), levels=[0.5, 1.5], colors="none", hatches=["//"]
        )
    if net_file is not None:
        shapes = read_lane_shapes(net_file)
        ax.add_collection(LineCollection(shapes, colors="#1b3a5c", linewidths=0.5))
        note = note or f"{len(shapes)} lanes from {net_file.name}."
    elif rf.network is not None:
        note = note or "network.json names no readable net file; lanes not drawn."
    if max(nx, ny) <= 60:  # cell borders (finer grids: they would hide the map)
        rows = [[(extent[0], y_top - r * ch), (extent[1], y_top - r * ch)] for r in range(nx + 1)]
        cols = [[(x_left + c * cw, extent[2]), (x_left + c * cw, extent[3])] for c in range(ny + 1)]
        ax.add_collection(LineCollection(rows + cols, colors="k", linewidths=0.3, alpha=0.5))
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(min(extent[2], extent[3]), max(extent[2], extent[3]))
    if rf.network is None or ch < 0:
        ax.invert_yaxis()
        ax.set_xlabel("column j")
        ax.set_ylabel("row i")
    else:
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
    for n, inc in enumerate(rf.incidents or [], start=1):  # scheduled incidents: numbered markers
        i, j = inc.get("cell") or (-1, -1)
        if 0 <= i < nx and 0 <= j < ny:
            x, y = x_left + (j + 0.5) * cw, y_top - (i + 0.5) * ch
            ax.plot(x, y, marker="X", ms=14, color="#d62728", mec="white", mew=1.5, zorder=5)
            ax.annotate(str(n), (x, y), xytext=(8, 8), textcoords="offset points",
                        color="#d62728", fontsize=11, fontweight="bold", zorder=5)  # fmt: skip
    ax.set_aspect("equal")
    fig.colorbar(image, ax=ax, shrink=0.7, label="peak importance over the horizon")
    ax.set_title(
        f"Monitoring grid {nx} x {ny} ({int(rf.obstacles.sum())} obstacle cells, hatched)"
        + (" over the road network" if net_file is not None else ""),
        fontsize=11,
    )
    return fig, note


MFD_QUALITY_KEYS = ("n_samples", "r2", "rmse_kmh", "online_r2", "online_rmse_kmh")


def mfd_quality(mfd: dict[str, Any]) -> str:
    """mfd.json's fit-quality figures, in lines short enough for a figure title."""

    def num(key: str, fmt: str) -> str | None:
        value = mfd.get(key)
        return format(value, fmt) if isinstance(value, (int, float)) else None

    lines = []
    n, r2, rmse = num("n_samples", "d"), num("r2", ".3f"), num("rmse_kmh", ".2f")
    if r2 is not None:
        lines.append(
            f"final fit: R2 = {r2}, RMSE = {rmse} km/h" + (f" over {n} samples" if n else "")
        )
    r2, rmse = num("online_r2", ".3f"), num("online_rmse_kmh", ".2f")
    if r2 is not None:
        lines.append(f"online fit (as the drones used it): R2 = {r2}, RMSE = {rmse} km/h")
    return "\n".join(lines)


def figure_mfd(rf: RunFiles) -> tuple[Figure, str]:
    """MFD samples (density, speed relative to the limit) with the fitted Underwood curve."""
    from twin.mfd import MFD

    mfd = rf.mfd or {}
    samples = rf.mfd_samples
    fig = Figure(figsize=(7.0, 4.6), layout="constrained")
    ax = fig.subplots()
    note = ""
    relative = samples is not None and "speed_limit" in samples.columns
    top = 1.0
    if samples is not None and {"density", "speed"} <= set(samples.columns):
        ok = np.isfinite(samples["speed"]) & np.isfinite(samples["density"])
        if relative:
            ok &= samples["speed_limit"] > 0
        rows = samples[ok]
        density = rows["density"].to_numpy(dtype=float)
        y = rows["speed"].to_numpy(dtype=float)
        if relative:
            y = y / rows["speed_limit"].to_numpy(dtype=float)
        if len(density) > 4000:
            hb = ax.hexbin(density, y, gridsize=70, bins="log", cmap="Blues", mincnt=1)
            fig.colorbar(hb, ax=ax, label="cell samples (log scale)")
        else:
            ax.scatter(density, y, s=5, alpha=0.35, color="#3a6ea5", label="cell samples")
        top = float(np.nanpercentile(density, 99.5)) if len(density) else 1.0
    else:
        note = "mfd_samples.parquet missing or without density/speed columns."
    grid = np.linspace(0.0, max(top, 1e-6), 200)
    fitted = all(
        isinstance(mfd.get(k), (int, float)) and np.isfinite(mfd[k]) and mfd[k] > 0
        for k in ("a", "k_c")
    )
    if fitted and relative:
        curve = MFD(float(mfd["a"]), float(mfd["k_c"])).speed_ratio(grid)
        ax.plot(grid, curve, "r-", lw=2.2,
                label=f"fit: v/v_lim = {mfd['a']:.3f} exp(-k / {mfd['k_c']:.1f})")  # fmt: skip
    else:
        note = (note + " " if note else "") + "No fitted curve drawn (mfd.json has no a, k_c)."
    ax.set_xlim(0, grid[-1])
    ax.set_xlabel(f"density k ({mfd.get('density_unit', 'veh per lane-km')})")
    ax.set_ylabel("speed / speed limit" if relative else "speed")
    quality = mfd_quality(mfd)
    ax.set_title(
        "Macroscopic fundamental diagram" + (f"\n{quality}" if quality else ""), fontsize=10
    )
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper right")
    return fig, note


def figure_surviving_paths(rf: RunFiles, trail: int = 60) -> Figure:
    """The live drones' paths over the first ``trail`` steps of each phase with drones lost
    (run.json ``faults``), one row per swarm and one column per phase, over ``T^k`` at the
    phase's first step; a lost drone is a grey cross where it stands."""
    plan = rf.faults
    live = rf.live()
    horizon = len(live) - 1
    phases = [p for p in plan.phases(horizon, live.shape[1]) if not live[p[0]].all()]
    swarms = rf.swarms
    fig = Figure(figsize=(3.6 * len(phases) + 1.2, 2.9 * len(swarms) + 0.8), layout="constrained")
    axes = fig.subplots(len(swarms), len(phases), squeeze=False)
    colours = drone_colours(live.shape[1])
    image = None
    for col, (a, b, label) in enumerate(phases):
        stop = min(b, a + trail, horizon)
        alive = np.flatnonzero(live[a])
        for row, swarm in enumerate(swarms):
            ax = axes[row][col]
            pos = rf.positions(swarm)
            image = draw_map(ax, rf.importance[a], rf.obstacles, "viridis", rf.importance_vmax)
            path = pos[a : stop + 1][:, alive]
            segments = np.transpose(path[:, :, ::-1], (1, 0, 2)).astype(float)
            live_colours = [colours[d] for d in alive]
            ax.add_collection(
                LineCollection(segments, colors=live_colours, linewidths=1.4, alpha=0.9),
                autolim=False,
            )
            ax.scatter(path[-1, :, 1], path[-1, :, 0], c=live_colours, edgecolors="white", s=40,
                       zorder=3)  # fmt: skip
            lost = pos[a][~live[a]]
            ax.scatter(lost[:, 1], lost[:, 0], marker="x", c="0.6", s=60, linewidths=2, zorder=4)
            ax.set_title(f"{swarm}, {label}: k = {a}..{stop}", fontsize=8)
    fig.colorbar(image, ax=axes.ravel().tolist(), shrink=0.6, label=importance_label(rf))
    fig.suptitle(
        f"Surviving drones' paths, first {trail} steps of each phase with drones lost "
        f"(crosses: lost drones; seed {rf.first_seed})",
        fontsize=11,
    )
    return fig


#: The swarm that plans on its own nowcast, drawn beside the best swarm by R_hat_T.
NOWCAST_SWARM = "nowcast-gain"


def belief_map_swarms(rf: RunFiles) -> list[str]:
    """The swarms whose nowcast the belief figures draw: the best by R_hat_T among those in
    ``belief_maps.npz``, and the swarm that plans on the nowcast when the run has it."""
    from twin.metrics import swarm_rows

    maps = rf.belief_maps or {}
    inside = list(maps.get("swarms", []))
    rows = swarm_rows(rf.summary)
    rows = rows[rows["swarm"].isin(inside)]
    chosen = [] if rows.empty else [str(rows.loc[rows["R_hat_T"].idxmax(), "swarm"])]
    if NOWCAST_SWARM in inside and NOWCAST_SWARM not in chosen:
        chosen.append(NOWCAST_SWARM)
    return chosen


def figure_belief_maps(rf: RunFiles) -> Figure:
    """True importance, then for each drawn swarm its nowcast's mean and std, at the steps of
    ``belief_maps.npz`` (columns), with the swarm's drones where they stood."""
    maps = rf.belief_maps
    swarms = belief_map_swarms(rf)
    steps = [int(k) for k in maps["steps"]]
    n_rows, n_cols = 1 + 2 * len(swarms), len(steps)
    vmax = rf.importance_vmax
    std_max = max(float(maps["std"][:, :, ~rf.obstacles].max(initial=0.0)), 1e-6)
    fig = Figure(figsize=(3.3 * n_cols + 1.2, 2.4 * n_rows + 0.6), layout="constrained")
    axes = np.atleast_2d(fig.subplots(n_rows, n_cols, squeeze=False))
    seed = maps["seed"]

    def label(k: int) -> str:
        clock = rf.clock(k)
        return f"k = {k}" + (f" ({clock})" if clock else "")

    images = {}
    for c, k in enumerate(steps):
        images["truth"] = draw_map(
            axes[0, c], maps["truth"][c], rf.obstacles, IMPORTANCE_CMAP, vmax
        )
        axes[0, c].set_title(f"true importance, {label(k)}", fontsize=9)
        for r, swarm in enumerate(swarms):
            s = maps["swarms"].index(swarm)
            ax_mean, ax_std = axes[1 + 2 * r, c], axes[2 + 2 * r, c]
            images["mean"] = draw_map(ax_mean, maps["mean"][s, c], rf.obstacles, IMPORTANCE_CMAP,
                                      vmax)  # fmt: skip
            images["std"] = draw_map(ax_std, maps["std"][s, c], rf.obstacles, "viridis", std_max)
            ax_mean.set_title(f"{swarm}: nowcast mean", fontsize=9)
            ax_std.set_title(f"{swarm}: nowcast std", fontsize=9)
            try:
                pos = rf.positions(swarm, seed)
            except Exception:  # a swarm without trajectories of this seed: maps alone
                continue
            if k < len(pos):
                colours = drone_colours(pos.shape[1])
                for ax in (ax_mean, ax_std):
                    draw_drones(ax, pos, k, 3, colours)
    fig.colorbar(images["truth"], ax=list(axes[: n_rows, -1]), shrink=0.5,
                 label="importance (truth and nowcast mean)")  # fmt: skip
    if "std" in images:
        fig.colorbar(images["std"], ax=list(axes[2::2, 0]), shrink=0.6, location="left",
                     label="nowcast std")  # fmt: skip
    fig.suptitle(f"Believed (nowcast) against true importance (seed {seed})", fontsize=11)
    return fig


def figure_belief_timeline(rf: RunFiles) -> Figure:
    """Each congestion event of ``belief_maps.npz`` as a bar over time; per drawn swarm (and the
    history alone) a mark at the step its nowcast first knew the event, a cross at the bar's end
    for one it never knew."""
    maps = rf.belief_maps
    swarms = belief_map_swarms(rf)
    onset, duration = maps["event_onset"], maps["event_duration"]
    order = np.lexsort((maps["event_j"], maps["event_i"], onset))[:MAX_EVENTS_DRAWN]
    n = max(len(order), 1)
    fig = Figure(figsize=(11, min(2.5 + 0.2 * n, 14)), layout="constrained")
    ax = fig.subplots()
    for y, e in enumerate(order):
        ax.barh(y, duration[e], left=onset[e], height=0.7, color="#f5b7b1", edgecolor="#7b241c",
                lw=0.4)  # fmt: skip
    rows = [("history alone", maps["history_known_at"], "#555555", "s")]
    colours = swarm_colours(rf.swarms)
    rows += [(s, maps["known_at"][maps["swarms"].index(s)], colours.get(s), "o") for s in swarms]
    for r, (name, known, colour, marker) in enumerate(rows):
        y = np.arange(len(order)) + (r - (len(rows) - 1) / 2) * 0.6 / len(rows)
        at = known[order]
        hit = at >= 0
        end = (onset + duration)[order]
        share = f"{100.0 * hit.mean():.0f}%" if len(order) else "-"
        ax.plot(at[hit], y[hit], marker, color=colour, ms=4, ls="none",
                label=f"{name}: known ({share})")  # fmt: skip
        ax.plot(end[~hit], y[~hit], "x", color=colour, ms=4, ls="none", label=f"{name}: never")
    ax.set_yticks(range(len(order)))
    ax.set_yticklabels([f"({maps['event_i'][e]}, {maps['event_j'][e]})" for e in order],
                       fontsize=6)  # fmt: skip
    ax.invert_yaxis()
    ax.set_xlim(0, rf.horizon + 1)
    ax.set_xlabel("step k" + _clock_note(rf))
    ax.set_ylabel("cell (i, j) of the event")
    ax.grid(alpha=0.3, axis="x")
    if len(order):
        ax.legend(fontsize=7, ncol=min(3, len(rows)), loc="upper right")
    fig.suptitle(
        f"When the nowcast knew each congestion event (seed {maps['seed']}, {len(onset)} events, "
        f"nowcast >= {maps['threshold']:g} while it lasts)",
        fontsize=11,
    )
    return fig
