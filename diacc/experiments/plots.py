"""Figures: training curves over seeds, and per-segment speed distributions.

* :func:`plot_curves`: collision rate, global reward and individual reward
  (the mean ego reward of the CAVs) against environment steps, one line per
  variant and setting (mean over the seeds of runs that differ only in their
  seed, :func:`run_groups`) with a shaded +-1 std band over seeds (a single seed has
  no band, and its legend says so). Every panel has its own legend; the
  collision rate keeps its [0, 1] axis, and a nearly flat reward curve gets
  an axis of at least +-5 % of its level instead of a magnified noise band.
  Each run is read from its
  ``progress.jsonl`` (written by the trainer), else from its TensorBoard
  event files; runs are grouped by ``config.json`` (variant, backend, and
  every other value that differs between the runs given).
* :func:`plot_speeds`: box plots of the per-vehicle speed samples by segment
  kind (multi-lane, 25 % and 50 % reduction), one box per policy, plus one
  Gaussian KDE panel per segment kind.

Both write ``<out>.png`` and ``<out>.pdf`` with matplotlib's Agg backend (no
display needed).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from diacc.errors import DiaccError
from diacc.experiments.evaluate import SPEEDS_FILE, load_episodes, read_csv
from diacc.fileio import atomic_target
from diacc.learn.progress import read_rows
from diacc.sim.maps import SEGMENT_KINDS
from diacc.tomlfile import read_json_object

#: Panel title -> progress keys tried in order (first one a run has is used).
CURVE_PANELS: dict[str, tuple[str, ...]] = {
    "Collision rate": ("episode/collision",),
    "Global reward": (
        "reward/global",
        "reward/global_reward",
        "episode/global_reward",
        "global_reward",
    ),
    # The mean ego reward r_e over the CAVs on the road (``reward/individual``), not
    # ``reward/ego_softmin``: the softmin-weighted sum follows the worst CAV ever
    # more closely as tau anneals, so it falls even while every CAV improves.
    "Individual reward": ("reward/individual",),
}
#: Colours per policy / variant, stable across figures.
PALETTE = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2")
#: Speed samples used per KDE (subsampled with a fixed seed beyond this).
KDE_MAX_SAMPLES = 20_000


class PlotError(DiaccError, ValueError):
    """Missing or unusable input to a plot command; one line."""


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def format_steps(steps: float, _position=None) -> str:
    """A step-axis tick label short enough not to overlap its neighbours: 0, 50k, 1.5M
    (plain numbers of 6-7 digits ran into each other on 4-panel curve figures)."""
    for scale, suffix in ((1e6, "M"), (1e3, "k")):
        if abs(steps) >= scale:
            return f"{steps / scale:.4g}{suffix}"
    return f"{steps:.4g}"


def step_axis(ax) -> None:
    """Label ``ax``'s x axis in environment steps with :func:`format_steps` ticks."""
    from matplotlib.ticker import FuncFormatter, MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(nbins=6, integer=True))
    ax.xaxis.set_major_formatter(FuncFormatter(format_steps))
    ax.set_xlabel("environment steps")


def _save(fig, out: str | Path) -> list[Path]:
    out = Path(out)
    if out.suffix in (".png", ".pdf"):
        out = out.with_suffix("")
    out.parent.mkdir(parents=True, exist_ok=True)
    paths = [out.with_suffix(".png"), out.with_suffix(".pdf")]
    for path in paths:
        with atomic_target(path) as tmp:  # never through a link; a reader sees a whole figure
            fig.savefig(tmp, dpi=150, bbox_inches="tight", format=path.suffix[1:])
    _pyplot().close(fig)
    return paths


# ----------------------------------------------------------------------------- training curves
def read_progress(run_dir: str | Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Series of a run: key -> (global_step (T,), value (T,)), from JSONL or TensorBoard."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise PlotError(f"run directory {run_dir} does not exist")
    series: dict[str, list[tuple[float, float]]] = {}
    progress = run_dir / "progress.jsonl"
    if progress.exists():
        for record in read_rows(progress):  # every row checked (types, UTF-8): one line
            for key, value in record.items():
                if value is not None:
                    series.setdefault(key, []).append((float(record["global_step"]), value))
    else:
        events = sorted((run_dir / "tb").glob("events.out.tfevents.*")) + sorted(
            run_dir.glob("events.out.tfevents.*")
        )
        if not events:
            raise PlotError(
                f"run directory {run_dir} has neither progress.jsonl nor TensorBoard logs"
            )
        from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

        for event_file in events:
            acc = EventAccumulator(str(event_file), size_guidance={"scalars": 0})
            acc.Reload()
            for tag in acc.Tags().get("scalars", []):
                key = tag.removeprefix("train/")
                series.setdefault(key, []).extend(
                    (float(e.step), float(e.value)) for e in acc.Scalars(tag)
                )
    if not series:
        raise PlotError(f"run directory {run_dir} has no logged values")
    out = {}
    for key, pairs in series.items():
        arr = np.array(sorted(pairs))  # (T, 2)
        out[key] = (arr[:, 0], arr[:, 1])
    return out


#: Config keys that never split curves: seeds are what a curve pools, the rest
#: decide where and how fast a run trains, not what it learns (a longer
#: ``total_steps`` is the same run trained further), or are in the name already.
CURVE_POOLED_KEYS = frozenset(
    {
        "seed",
        "run_dir",
        "total_steps",
        "device",
        "torch_threads",
        "vector",
        "checkpoint_every",
        "variant",
        "backend",
        "env.backend",
        "env.use_psar",
    }
)


def run_groups(run_dirs: list[Path]) -> dict[Path, str]:
    """Run dir -> curve label: ``variant (backend)``, plus every config value that
    differs between the runs given (a sweep's setting, e.g. ``tau_final=0.05``).

    Runs that differ only in their seed (or in :data:`CURVE_POOLED_KEYS`) share a
    label and are pooled into one mean +- std curve; runs of different settings
    never are. Keys missing from some run's ``config.json`` (it predates them)
    are not compared.
    """
    from diacc.config import flatten_config
    from diacc.experiments.sweepaxes import format_value, short_keys

    configs = {}
    for d in run_dirs:
        try:
            configs[d] = flatten_config(read_json_object(d / "config.json", PlotError))
        except PlotError:  # no or a damaged config.json: labelled by its name
            continue
    first = next(iter(configs.values()), {})  # its key order is the config's field order
    differing = [
        k
        for k in first
        if k not in CURVE_POOLED_KEYS
        and all(k in c for c in configs.values())
        and len({json.dumps(c[k], default=str) for c in configs.values()}) > 1
    ]
    short = short_keys(differing)
    labels = {}
    for run_dir in run_dirs:
        if run_dir not in configs:
            labels[run_dir] = run_dir.name
            continue
        flat = configs[run_dir]
        # ``env.backend`` since the config tree was nested; top-level in older runs
        backend = flat.get("env.backend", flat.get("backend", "?"))
        label = f"{flat.get('variant', run_dir.name)} ({backend})"
        setting = ", ".join(f"{short[k]}={format_value(flat[k])}" for k in differing)
        labels[run_dir] = f"{label} {setting}" if setting else label
    return labels


def _smooth(values: np.ndarray, window: int) -> np.ndarray:
    if window <= 1 or values.size < window:
        return values
    kernel = np.ones(window) / window
    padded = np.concatenate([np.full(window - 1, values[0]), values])
    return np.convolve(padded, kernel, mode="valid")


def group_curves(
    run_dirs: list[str | Path], key_options: tuple[str, ...], smooth: int = 1
) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Group -> (steps (T,), mean (T,), std (T,)) over the runs of the group."""
    return {g: c[:3] for g, c in _group_curves(run_dirs, key_options, smooth).items()}


def _group_curves(
    run_dirs: list[str | Path], key_options: tuple[str, ...], smooth: int = 1
) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, int]]:
    """Group -> (steps (T,), mean (T,), std (T,), number of runs).

    Runs of a group are interpolated onto the steps of the run with the fewest
    points, inside the range that all runs cover.
    """
    runs: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
    groups = run_groups([Path(d) for d in run_dirs])
    for run_dir, group in groups.items():
        series = read_progress(run_dir)
        key = next((k for k in key_options if k in series), None)
        if key is None:
            continue
        steps, values = series[key]
        runs.setdefault(group, []).append((steps, _smooth(values, smooth)))
    out = {}
    for group, members in runs.items():
        end = min(s[-1] for s, _ in members)
        start = max(s[0] for s, _ in members)
        grid = min((s for s, _ in members), key=len)
        grid = grid[(grid >= start) & (grid <= end)]
        stacked = np.stack([np.interp(grid, s, v) for s, v in members])  # (R, T)
        out[group] = (grid, stacked.mean(0), stacked.std(0), len(members))
    return out


#: Panels whose values are shares in [0, 1], drawn on a fixed axis.
SHARE_PANELS = ("Collision rate",)


def _y_limits(title: str, lo: float, hi: float) -> tuple[float, float]:
    """Axis range: [0, 1] for shares; at least +-5 % of the level (or +-0.05) otherwise."""
    if title in SHARE_PANELS:
        return -0.03, 1.03
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    half = max(half * 1.1, 0.05 * max(abs(centre), 1.0))
    return centre - half, centre + half


def plot_curves(run_dirs: list[str | Path], out: str | Path, smooth: int = 1) -> list[Path]:
    """Training curves of several runs (see module docstring); returns the files written."""
    if not run_dirs:
        raise PlotError("give at least one run directory")
    panels = {title: _group_curves(run_dirs, keys, smooth) for title, keys in CURVE_PANELS.items()}
    if not any(panels.values()):
        raise PlotError("none of the runs logged a collision rate, global or individual reward")
    plt = _pyplot()
    groups = sorted({g for curves in panels.values() for g in curves})
    colour = {g: PALETTE[i % len(PALETTE)] for i, g in enumerate(groups)}
    fig, axes = plt.subplots(1, len(panels), figsize=(5 * len(panels), 3.8))
    for ax, (title, curves) in zip(np.atleast_1d(axes), panels.items(), strict=True):
        lo, hi = np.inf, -np.inf
        for group, (steps, mean, std, n_runs) in sorted(curves.items()):
            band = "1 seed, no band" if n_runs == 1 else f"mean ± std of {n_runs} seeds"
            ax.plot(steps, mean, color=colour[group], label=f"{group}: {band}", lw=1.5)
            if n_runs > 1:
                ax.fill_between(
                    steps, mean - std, mean + std, color=colour[group], alpha=0.25, lw=0
                )
            lo, hi = min(lo, float((mean - std).min())), max(hi, float((mean + std).max()))
        ax.set_title(title if curves else f"{title} (not logged)")
        step_axis(ax)
        ax.set_ylabel("share of episodes" if title in SHARE_PANELS else "mean reward per step")
        if curves:
            ax.set_ylim(*_y_limits(title, lo, hi))
            ax.legend(fontsize=7, loc="best")
        ax.grid(alpha=0.3)
    fig.tight_layout()
    return _save(fig, out)


# ----------------------------------------------------------------------------- speeds
def load_speeds_by_map(result_dir: str | Path) -> tuple[str, dict[str, dict[str, np.ndarray]]]:
    """(policy label, map -> segment kind -> speed samples (S,)) of one results directory.

    One pass over the speeds file for every map in it (``diacc reproduce``
    draws one figure per map from the same directories).
    """
    meta, _ = load_episodes(result_dir)
    path = Path(result_dir) / SPEEDS_FILE
    if not path.exists():
        raise PlotError(f"results directory {result_dir} has no {SPEEDS_FILE}")
    rows = read_csv(path)
    maps = np.array([r["map"] for r in rows])
    kinds = np.array([r["segment_kind"] for r in rows])
    speeds = np.array([float(r["speed_mps"]) for r in rows])
    by_map = {
        m: {kind: speeds[(maps == m) & (kinds == kind)] for kind in SEGMENT_KINDS}
        for m in dict.fromkeys(maps.tolist())
    }
    return meta["policy"], by_map


def load_speeds(
    result_dir: str | Path, map_name: str | None = None
) -> tuple[str, dict[str, np.ndarray]]:
    """(policy label, segment kind -> speed samples (S,)) of one results directory."""
    label, by_map = load_speeds_by_map(result_dir)
    if map_name is None:
        return label, {
            kind: np.concatenate([by_kind[kind] for by_kind in by_map.values()] or [np.zeros(0)])
            for kind in SEGMENT_KINDS
        }
    if map_name not in by_map:
        raise PlotError(f"results directory {result_dir} has no speed samples on map {map_name!r}")
    return label, by_map[map_name]


def gaussian_kde(samples: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Gaussian KDE with Scott's bandwidth, evaluated on ``grid`` (G,)."""
    samples = np.asarray(samples, float)
    if samples.size > KDE_MAX_SAMPLES:
        samples = np.random.default_rng(0).choice(samples, KDE_MAX_SAMPLES, replace=False)
    std = samples.std()
    bandwidth = max(std, 1e-3) * samples.size ** (-1 / 5)
    z = (grid[:, None] - samples[None, :]) / bandwidth  # (G, S)
    return np.exp(-0.5 * z**2).sum(1) / (samples.size * bandwidth * np.sqrt(2 * np.pi))


def plot_speeds(
    result_dirs: list[str | Path], out: str | Path, map_name: str | None = None
) -> list[Path]:
    """Per-segment-kind speed box plots and KDEs, one colour per policy, one figure per map.

    Maps are never pooled: with ``map_name`` the figure shows that map; without
    it, a results set of one map gives ``<out>.png``, and one of several maps
    gives ``<out>-<map>.png`` per map. The caption names the backend(s), the
    map and the episodes behind each policy.
    """
    if not result_dirs:
        raise PlotError("give at least one results directory")
    loaded = [_speed_source(d) for d in result_dirs]
    labels = [src["label"] for src in loaded]
    if len(set(labels)) < len(labels):
        labels = [f"{lab} [{Path(d).name}]" for lab, d in zip(labels, result_dirs, strict=True)]
    maps = list(dict.fromkeys(m for src in loaded for m in src["by_map"]))
    if map_name is not None:
        missing = [
            d for d, src in zip(result_dirs, loaded, strict=True) if map_name not in src["by_map"]
        ]
        if missing:
            raise PlotError(
                f"results directory {missing[0]} has no speed samples on map {map_name!r}"
            )
        maps = [map_name]
    backends = sorted({src["backend"] for src in loaded})
    paths = []
    for m in maps:
        columns = [
            (lab, src["by_map"].get(m, _no_speeds()))
            for lab, src in zip(labels, loaded, strict=True)
        ]
        episodes = ", ".join(
            f"{lab}: {src['episodes'].get(m, 0)}" for lab, src in zip(labels, loaded, strict=True)
        )
        caption = (
            f"Backend {' and '.join(backends)}, map {m}. Episodes per policy: {episodes}. "
            "Boxes: quartiles and median (black line) of all vehicle-step speed samples, "
            "whiskers 1.5 IQR, outliers hidden; curves: Gaussian KDE of the same samples."
        )
        target = out if len(maps) == 1 else _suffixed(out, Path(m).stem)
        paths += draw_speeds(columns, target, f"Speeds on {m} ({', '.join(backends)})", caption)
    return paths


def _speed_source(result_dir: str | Path) -> dict:
    """Label, backend, map -> kind -> samples and map -> episode count of a results directory."""
    meta, rows = load_episodes(result_dir)
    label, by_map = load_speeds_by_map(result_dir)
    episodes: dict[str, int] = {}
    for row in rows:
        episodes[row["map"]] = episodes.get(row["map"], 0) + 1
    return {
        "label": label,
        "backend": meta.get("backend", "?"),
        "by_map": by_map,
        "episodes": episodes,
    }


def _no_speeds() -> dict[str, np.ndarray]:
    return {kind: np.zeros(0) for kind in SEGMENT_KINDS}


def _suffixed(out: str | Path, suffix: str) -> Path:
    out = Path(out)
    if out.suffix in (".png", ".pdf"):
        out = out.with_suffix("")
    return out.with_name(f"{out.name}-{suffix}")


def draw_speeds(
    loaded: list[tuple[str, dict[str, np.ndarray]]],
    out: str | Path,
    title: str | None = None,
    caption: str | None = None,
) -> list[Path]:
    """The figure of :func:`plot_speeds` from (label, segment kind -> samples (S,)) per policy.

    Boxes are light (alpha 0.45) with a black median line, so the median
    stays visible on any box colour; every density panel has its axis labels
    and a legend; ``caption`` goes under the figure.
    """
    kinds = [k for k in SEGMENT_KINDS if any(by_kind[k].size for _, by_kind in loaded)]
    if not kinds:
        raise PlotError("no speed samples to plot")
    plt = _pyplot()
    fig, axes = plt.subplots(1, 1 + len(kinds), figsize=(4.5 * (1 + len(kinds)), 4.0))
    box_ax, kde_axes = axes[0], axes[1:]
    width = 0.8 / len(loaded)
    for p, (label, by_kind) in enumerate(loaded):
        colour = PALETTE[p % len(PALETTE)]
        data = [by_kind[k] if by_kind[k].size else np.array([np.nan]) for k in kinds]
        positions = np.arange(len(kinds)) + (p - (len(loaded) - 1) / 2) * width
        parts = box_ax.boxplot(
            data,
            positions=positions,
            widths=width * 0.9,
            patch_artist=True,
            showfliers=False,
            manage_ticks=False,
            medianprops={"color": "black", "linewidth": 1.6},
        )
        for patch in parts["boxes"]:
            patch.set_facecolor(colour)
            patch.set_alpha(0.45)
            patch.set_edgecolor(colour)
        box_ax.plot([], [], color=colour, lw=6, alpha=0.45, label=label)
        for ax, kind in zip(kde_axes, kinds, strict=True):
            if by_kind[kind].size:
                hi = max(30.0, float(by_kind[kind].max()) + 2)
                grid = np.linspace(0.0, hi, 300)
                density = gaussian_kde(by_kind[kind], grid)
                ax.plot(grid, density, color=colour, label=f"{label} (n = {by_kind[kind].size})")
    box_ax.plot([], [], color="black", lw=1.6, label="median")
    box_ax.set_xticks(np.arange(len(kinds)), kinds)
    box_ax.set_xlabel("segment kind")
    box_ax.set_ylabel("speed (m/s)")
    box_ax.set_title("Speed by segment kind")
    box_ax.grid(axis="y", alpha=0.3)
    box_ax.legend(fontsize=8)
    for ax, kind in zip(kde_axes, kinds, strict=True):
        ax.set_title(f"Speed density: {kind}")
        ax.set_xlabel("speed (m/s)")
        ax.set_ylabel("density (per m/s)")
        ax.set_ylim(bottom=0.0)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    if caption:
        fig.text(0.01, -0.01, caption, fontsize=8.5, ha="left", va="top", wrap=True)
    return _save(fig, out)
