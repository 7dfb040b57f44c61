"""Pictures people look at: false-colour maps (sample counts, selected scales) and
log-log convergence plots, written atomically as PNG with matplotlib's Agg backend."""

from __future__ import annotations

import numpy as np

from ._atomic import atomic_path
from .errors import InputError, as_float_array, check_finite

__all__ = ["write_map_png", "write_convergence_plot"]


def _pyplot():
    import matplotlib
    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    return plt


def _save(plt, fig, path, protect) -> None:
    """Lay out ``fig``, write it atomically as PNG to ``path``, and free it."""
    try:
        fig.tight_layout()
        with atomic_path(path, protect=protect) as tmp:
            fig.savefig(tmp, format="png")
    finally:
        plt.close(fig)


def write_map_png(path, values, *, cmap: str = "viridis", label: str = "", log: bool = False,
                  protect=()) -> None:
    """A false-colour PNG of an ``(H, W)`` map with a colour bar (e.g. sample counts)."""
    v = as_float_array("values", values, ndim=2)
    check_finite("values", v)
    plt = _pyplot()
    from matplotlib.colors import LogNorm
    h, w = v.shape
    fig, ax = plt.subplots(figsize=(max(3.0, 4.0 * w / max(h, w)) + 1.0, max(3.0, 4.0 * h / max(h, w))),
                           dpi=100)
    norm = LogNorm(vmin=max(v[v > 0].min(), 1e-12) if (v > 0).any() else 1, vmax=max(v.max(), 1e-12)) \
        if log and (v > 0).any() else None
    im = ax.imshow(v, cmap=cmap, norm=norm, interpolation="nearest")
    ax.set_axis_off()
    fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04, label=label)
    _save(plt, fig, path, protect)


def write_convergence_plot(path, series: dict, *, xlabel: str = "samples per pixel",
                           ylabel: str = "relMSE", title: str = "", protect=()) -> None:
    """A log-log plot of ``{label: (x, y)}`` curves (error against spp), as PNG."""
    if not series:
        raise InputError("`series` must hold at least one curve.")
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 4.2), dpi=110)
    for label, (x, y) in series.items():
        x = np.asarray(x, float)
        y = np.asarray(y, float)
        if x.shape != y.shape:
            raise InputError(f"curve {label!r}: x {x.shape} and y {y.shape} differ in shape.")
        ax.loglog(x, y, "o-", label=label)
    xs = sorted({float(v) for x, _ in series.values() for v in np.ravel(x)})
    if 0 < len(xs) <= 12:  # label the measured sample counts plainly (4, 16, 64, ...)
        from matplotlib.ticker import NullFormatter
        ax.set_xticks(xs)
        ax.set_xticklabels([f"{v:g}" for v in xs])
        ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    _save(plt, fig, path, protect)
