"""PNG plots of a run: the quantities of the paper's Fig. 2 and Fig. 3.

Fig. 2 is the average attitude error norm ``(1/n_f) Σ |R̃_i|_I``; Fig. 3 the average position
error norm ``(1/n_f) Σ ‖p̃_i‖`` with ``p̃_i = p_i − R̃_i p̂_i``. Each figure has the paper's linear
view and a log view showing the convergence rate, with per-follower curves.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .results import Recording


def _figure(t: np.ndarray, per_agent: np.ndarray, names: list[str], title: str, ylabel: str,
            path: Path) -> None:
    import matplotlib
    matplotlib.use('Agg')  # files only: works without a display
    import matplotlib.pyplot as plt

    mean = per_agent.mean(axis=1)
    fig, (lin, lg) = plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
    for ax, log in ((lin, False), (lg, True)):
        for k, name in enumerate(names[:20]):  # beyond 20 curves a legend is noise
            ax.plot(t, per_agent[:, k], lw=0.8, alpha=0.6, label=name)
        ax.plot(t, mean, 'k', lw=2.0, label='average')
        ax.set_xlabel('time [s]')
        ax.grid(True, which='both', alpha=0.3)
        if log:
            ax.set_yscale('log')
            ax.set_title(f'{title} (log scale)')
        else:
            ax.set_ylabel(ylabel)
            ax.set_title(title)
    lin.legend(fontsize=7, ncol=2)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_plots(rec: Recording, out_dir: Path) -> list[Path]:
    """Write ``fig2_attitude_error.png`` and ``fig3_position_error.png``; return their paths."""
    att = out_dir / 'fig2_attitude_error.png'
    pos = out_dir / 'fig3_position_error.png'
    # Floor at a tiny positive value so a log axis can show exact zeros (leaders, converged).
    _figure(rec.t, np.maximum(rec.att_dist_I, 1e-17), rec.followers,
            'Average attitude estimation error norm (Fig. 2)', r'$|\tilde R_i|_I$', att)
    _figure(rec.t, np.maximum(rec.pos_err_paper, 1e-17), rec.followers,
            'Average position estimation error norm (Fig. 3)',
            r'$\|p_i - \tilde R_i \hat p_i\|$ [m]', pos)
    return [att, pos]


def write_compare_plot(recs: dict[str, Recording], path: Path,
                       dashed: frozenset[str] = frozenset()) -> Path:
    """Mean attitude and position errors of several runs (label -> recording), overlaid (log
    scale); labels in ``dashed`` (the distributed runs) are drawn dashed over the others."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, (att, pos) = plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
    colours: dict[str, str] = {}  # one per method: a method's DDS run shares its colour
    for label, rec in recs.items():
        colour = colours.setdefault(label.split(' (')[0], f'C{len(colours)}')
        style: dict[str, Any] = ({'ls': '--', 'lw': 1.2} if label in dashed
                                 else {'lw': 1.8, 'alpha': 0.8})
        style['color'] = colour
        att.plot(rec.t, np.maximum(rec.att_err.mean(axis=1), 1e-17), label=label, **style)
        pos.plot(rec.t, np.maximum(rec.pos_err.mean(axis=1), 1e-17), label=label, **style)
    log_axes(att, 'Mean attitude error', 'time [s]', 'angle of $R_i \\hat R_i^T$ [rad]')
    log_axes(pos, 'Mean position error', 'time [s]', r'$\|p_i - \hat p_i\|$ [m]')
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def log_axes(ax: Any, title: str, xlabel: str, ylabel: str, log_x: bool = False,
             legend_size: int = 8) -> None:
    """Log-scale axes with titles, a grid and a legend: the look of every comparison plot."""
    if log_x:
        ax.set_xscale('log')
    ax.set_yscale('log')
    ax.set_title(title)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, which='both', alpha=0.3)
    ax.legend(fontsize=legend_size)
