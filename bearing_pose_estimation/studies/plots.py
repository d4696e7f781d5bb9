"""PNG plots of a run: Boughellaba & Tayebi's Fig. 2, the average ``|R̃_i|_I``, and Fig. 3, the
average ``‖p_i − R̃_i p̂_i‖``, each in the paper's linear view and a log view, per follower; De
Carli et al.'s cascade, Presenza et al.'s errors by role, the methods compared and a moving
fleet's trajectories."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from ..metrics.results import Recording


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the Agg backend (files only: works without a display)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    return plt


def save(fig: Any, path: Path) -> Path:
    """Write ``fig`` to ``path`` (110 dpi) and close it."""
    fig.savefig(path, dpi=110)
    pyplot().close(fig)
    return path


def _figure(t: np.ndarray, per_agent: np.ndarray, names: list[str], title: str, ylabel: str,
            path: Path) -> None:
    plt = pyplot()
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
    save(fig, path)


def write_plots(rec: Recording, out_dir: Path) -> list[Path]:
    """Write ``fig2_attitude_error.png`` and ``fig3_position_error.png``; return their paths."""
    att, pos = out_dir / 'fig2_attitude_error.png', out_dir / 'fig3_position_error.png'
    # Floor at a tiny positive value so a log axis can show exact zeros (leaders, converged).
    _figure(rec.t, np.maximum(rec.att_dist_I, 1e-17), rec.followers,
            'Average attitude estimation error norm (Fig. 2)', r'$|\tilde R_i|_I$', att)
    _figure(rec.t, np.maximum(rec.pos_err_paper, 1e-17), rec.followers,
            'Average position estimation error norm (Fig. 3)',
            r'$\|p_i - \tilde R_i \hat p_i\|$ [m]', pos)
    return [att, pos]


ROLES_PLOT = 'errors_by_role.png'
ROLES_CSV = 'errors_by_role.csv'


def write_role_outputs(rec: Recording, groups: dict[str, list[str]], out_dir: Path,
                       title: str = '', plot: bool = True) -> list[Path]:
    """Robots by role (sensing, free): :data:`ROLES_CSV` (``t``, per group its mean position [m]
    and attitude [rad] errors) and :data:`ROLES_PLOT`; nothing without groups."""
    if not groups:
        return []
    cols = {g: [rec.followers.index(a) for a in names if a in rec.followers]
            for g, names in groups.items()}
    cols = {g: c for g, c in cols.items() if c}
    csv_path = out_dir / ROLES_CSV
    header = ['t'] + [f'{g}_{q}' for g in cols for q in ('position_error_mean_m',
                                                           'attitude_error_mean_rad')]
    table = np.column_stack([rec.t] + [x[:, c].mean(axis=1) for c in cols.values()
                                       for x in (rec.pos_err, rec.att_err)])
    np.savetxt(csv_path, table, delimiter=',', header=','.join(header), comments='',
               fmt='%.9e')
    if not plot:
        return [csv_path]
    plt = pyplot()
    styles = ['-', '--', ':', '-.']
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
    for ax, values, name, unit in ((axes[0], rec.pos_err, 'position error', 'm'),
                                   (axes[1], rec.att_err, 'attitude error', 'rad')):
        shown = np.where(values > 0, values, np.nan)   # an exact 0 (the anchor at t = 0)
        for (group, c), style in zip(cols.items(), styles):   # has no place on a log axis
            for k in c:
                ax.plot(rec.t, shown[:, k], style, lw=0.9, alpha=0.7,
                        label=f'{rec.followers[k]} ({group})')
            ax.plot(rec.t, values[:, c].mean(axis=1), style, color='k', lw=2.0,
                    label=f'{group} robots, mean')
        log_axes(ax, f'{name} per robot', 'time [s]', unit, legend_size=6)
    if title:
        fig.suptitle(title)
    return [csv_path, save(fig, out_dir / ROLES_PLOT)]


CASCADE_PLOT = 'cascade.png'


def plot_cascade(rec: Recording, path: Path, title: str = '') -> Path | None:
    """One panel per stage of the cascade (pairs' relative yaw, yaw, position, formation), or
    None (nothing written) without per-pair errors."""
    pairs = {k: v for k, v in rec.extra.items() if k.startswith('rel_yaw_err_')}
    if not pairs:
        return None
    plt = pyplot()
    formation = {k: v for k, v in rec.extra.items() if k.startswith('formation_err_')}
    panels = [('(a) relative yaw per pair', r'$|\hat z_{ij} - e^{\iota\psi_{ij}}|$',
               np.array(list(pairs.values())).T, [k[len('rel_yaw_err_'):] for k in pairs]),
              ('(b) yaw per robot (aligned)', 'rad', rec.att_err, rec.followers),
              ('(c) position per robot (aligned)', 'm', rec.pos_err, rec.followers)]
    if formation:
        panels.append(('(d) formation per robot', 'm', np.array(list(formation.values())).T,
                       [k[len('formation_err_'):].removesuffix('_m') for k in formation]))
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.8),
                             constrained_layout=True)
    for ax, (name, unit, values, labels) in zip(axes, panels):
        for k, label in enumerate(labels[:20]):
            ax.plot(rec.t, np.maximum(values[:, k], 1e-17), lw=0.8, alpha=0.6, label=label)
        finite = np.isfinite(values)   # a pair's state starts at the first step
        mean = np.where(finite, values, 0.0).sum(axis=1) / np.maximum(finite.sum(axis=1), 1)
        ax.plot(rec.t, np.where(finite.any(axis=1), np.maximum(mean, 1e-17), np.nan), 'k',
                lw=2.0, label='mean')
        log_axes(ax, name, 'time [s]', unit, legend_size=None)
    axes[0].legend(fontsize=6, ncol=2)
    if title:
        fig.suptitle(title)
    return save(fig, path)


def write_compare_plot(recs: dict[str, Recording], path: Path,
                       dashed: frozenset[str] = frozenset()) -> Path:
    """Mean attitude and position errors of several runs (label -> recording), overlaid, log
    scale; labels in ``dashed`` (the distributed runs) dashed."""
    plt = pyplot()
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
    return save(fig, path)


def log_axes(ax: Any, title: str, xlabel: str, ylabel: str, log_x: bool = False,
             legend_size: int | None = 8) -> None:
    """Log-scale axes with titles, a grid and a legend (``legend_size`` None: none)."""
    if log_x:
        ax.set_xscale('log')
    ax.set_yscale('log')
    ax.set_title(title)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, which='both', alpha=0.3)
    if legend_size is not None:
        ax.legend(fontsize=legend_size)


TRAJECTORY_PLOT = 'trajectories.png'
MAX_TRAJECTORIES = 20  # beyond this many agents the picture is a tangle: draw a sample


def _shown_agents(is_leader: np.ndarray, limit: int) -> np.ndarray:
    """Rows to draw: all if at most ``limit``, else the leaders and followers spread evenly."""
    n = len(is_leader)
    if n <= limit:
        return np.arange(n)
    leaders = np.flatnonzero(is_leader)[:limit]
    others = np.flatnonzero(~is_leader)
    room = limit - len(leaders)
    if room <= 0 or not len(others):
        return leaders
    spread = np.unique(np.linspace(0, len(others) - 1, room).round().astype(int))
    return np.sort(np.concatenate([leaders, others[spread]]))


def _agent_colours(n: int) -> list[Any]:
    """``n`` (at most 20) distinct colours: the default cycle, then tab20's dark shades before
    its light ones (so neighbouring agents do not get two shades of one hue)."""
    if n <= 10:
        return [f'C{k}' for k in range(n)]
    import matplotlib

    cmap = matplotlib.colormaps['tab20']
    return [cmap(k) for k in [*range(0, 20, 2), *range(1, 20, 2)][:n]]


def _equal_box(ax: Any, points: np.ndarray) -> None:
    """Limits around the finite ``points`` ``(M, 3)``, one metre as long on every axis."""
    finite = points[np.isfinite(points).all(axis=1)]
    if not len(finite):
        return
    lo, hi = finite.min(axis=0), finite.max(axis=0)
    # A flat (or point-like) set still gets a visible box: at least 15 % of the largest range.
    span = np.maximum(hi - lo, 0.15 * max(float((hi - lo).max()), 1e-3))
    mid, half = (lo + hi) / 2, 0.52 * span
    for k, set_lim in enumerate((ax.set_xlim, ax.set_ylim, ax.set_zlim)):
        set_lim(mid[k] - half[k], mid[k] + half[k])
    ax.set_box_aspect(tuple(span), zoom=1.0)


def plot_trajectories(rec: Recording, path: Path, title: str | None = None) -> Path:
    """The true (solid) and estimated (dashed, world frame) trajectories in 3D, one colour per
    agent (at most :data:`MAX_TRAJECTORIES`), beside the followers' position errors."""
    from matplotlib.lines import Line2D
    from matplotlib.ticker import MaxNLocator

    plt = pyplot()
    tr = rec.trajectories
    if tr is None:
        raise ValueError('the recording has no trajectories (only moving fleets record them)')
    n = len(tr.agents)
    is_leader = tr.is_leader
    shown = _shown_agents(is_leader, MAX_TRAJECTORIES)
    colours = dict(zip(shown.tolist(), _agent_colours(len(shown))))

    fig = plt.figure(figsize=(14, 6.2), constrained_layout=True)
    # The legend gets its own column: next to the 3D box it would cover the z tick labels.
    grid = fig.add_gridspec(1, 3, width_ratios=[1.5, 0.24, 1.0])
    ax = fig.add_subplot(grid[0], projection='3d')
    legend_ax = fig.add_subplot(grid[1])
    legend_ax.axis('off')
    err = fig.add_subplot(grid[2])
    for i in shown.tolist():
        c, lead = colours[i], bool(is_leader[i])
        p, q = tr.p[:, i], tr.p_hat[:, i]
        ax.plot(p[:, 0], p[:, 1], p[:, 2], color=c, lw=2.4 if lead else 1.6, alpha=0.9)
        if not lead:  # a leader's estimate is its truth: the dashed line would hide under it
            ax.plot(q[:, 0], q[:, 1], q[:, 2], color=c, lw=0.9, ls='--', alpha=0.9)
            ax.scatter(*q[0], color=c, marker='o', s=22, facecolors='none', linewidths=1.0,
                       depthshade=False)
        ax.scatter(*p[0], color=c, marker='*' if lead else 'o', s=110 if lead else 26,
                   edgecolors='k', linewidths=0.5, depthshade=False, zorder=5)
    _equal_box(ax, np.concatenate([tr.p[:, shown].reshape(-1, 3),
                                   tr.p_hat[:, shown[~is_leader[shown]]].reshape(-1, 3)]))
    ax.set(xlabel='x [m]', ylabel='y [m]', zlabel='z [m]')
    ax.tick_params(labelsize=8)
    for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
        axis.set_major_locator(MaxNLocator(6, steps=[1, 2, 5, 10]))
    ax.view_init(elev=24, azim=-58)
    some = f'{len(shown)} of {n} agents shown' if len(shown) < n else f'{n} agents'
    ax.set_title(f'Trajectories in the world frame ({some})', fontsize=11)

    key = [Line2D([], [], color='0.25', label=label, **style) for label, style in (
        ('true', dict(lw=1.6)), ('estimate', dict(lw=0.9, ls='--')),
        ('start (true)', dict(marker='o', ls='', ms=5, mec='k', mew=0.5)),
        ('start (estimate)', dict(marker='o', ls='', ms=5, mfc='none')),
        ('leader (knows its pose)', dict(marker='*', ls='', ms=10, mec='k', mew=0.5)))]
    if len(shown) <= 12:   # a key per agent
        key += [Line2D([], [], color=colours[i], lw=2.4 if is_leader[i] else 1.6,
                       label=tr.agents[i] + (' (leader)' if is_leader[i] else ''))
                for i in shown.tolist()]
    legend_ax.legend(handles=key, loc='center', fontsize=8, frameon=False)

    column = {name: k for k, name in enumerate(rec.followers)}
    for i in shown.tolist():
        k = column.get(tr.agents[i])
        if k is not None:
            err.plot(rec.t, np.maximum(rec.pos_err[:, k], 1e-17), color=colours[i], lw=1.0,
                     alpha=0.85, label=tr.agents[i])
    if rec.pos_err.shape[1]:
        err.plot(rec.t, np.maximum(rec.pos_err.mean(axis=1), 1e-17), 'k', lw=2.0,
                 label=f'average ({rec.pos_err.shape[1]} followers)')
        err.legend(handles=err.get_lines()[-1:], fontsize=8)  # agents' colours: centre key
    err.set(yscale='log', xlabel='time [s]', ylabel=r'$\|p_i - \hat p_i\|$ [m] (world frame)')
    err.set_title('Position error: the gap between dashed and solid', fontsize=11)
    err.grid(True, which='major', alpha=0.35)
    err.grid(True, which='minor', alpha=0.12)
    fig.suptitle(title or 'True and estimated trajectories', fontsize=12)
    return save(fig, path)
