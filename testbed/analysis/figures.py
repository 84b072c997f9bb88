"""PNG figures of the analysis (matplotlib, Agg backend, imported lazily).

* :func:`plot_time_series`: x_k, u_k and E_k over time with the DoS intervals
  shaded (the paper's second figure);
* :func:`plot_phase_portrait`: the nominal region of attraction (gray), trajectories
  (one escaping), optionally the vulnerable states of a budget (the third figure);
* :func:`plot_allowable_region`: Theorem 1's boundary in the (rho_D, rho_F) plane
  for the plain, optimized and tight choices over the empirical convergence map
  of a sweep (the fourth figure, plus the experiment);
* :func:`plot_delta`: delta (Lemma 2) and the E_0 bound (Theorem 2) against gamma;
* :func:`plot_vulnerability`: the least DoS duration that defeats the loop over the region of
  attraction, with Theorem 2's delta-ball (the figure the paper's conclusion asks for).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np


def _plt():
    os.environ.setdefault("MPLBACKEND", "Agg")
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=130, bbox_inches="tight")
    _plt().close(fig)
    return path


def dos_spans(theta, T: float, intervals=None) -> list[tuple[float, float]]:
    """Time spans to shade: the attack intervals if given, else [t_k, t_{k+1}) over runs of theta_k = 1."""
    if intervals is not None:
        return [(a, a + max(tau, 0.0)) for a, tau in intervals]
    th = np.asarray(theta).astype(bool)
    if not th.any():
        return []
    d = np.diff(np.concatenate(([0], th.astype(np.int8), [0])))
    starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    return [(s * T, e * T) for s, e in zip(starts, ends)]


def plot_time_series(res, path, *, title: str = "", intervals=None):
    """States, input and quantizer range E_k against time, DoS shaded (paper, Fig. 2).

    Parameters
    ----------
    res : a ``testbed.simulate.SimResult``.
    intervals : attack intervals [(a_i, tau_i), ...] to shade (default: runs of lost samples).
    """
    plt = _plt()
    spans = dos_spans(res.theta, res.T, intervals)
    fig, axs = plt.subplots(3, 1, figsize=(7.0, 6.5), sharex=True)
    t = res.t
    for i in range(res.x.shape[1]):
        axs[0].plot(t, res.x[:, i], lw=1.3, label=f"$x_{i + 1}$")
    axs[0].set_ylabel("state")
    axs[0].legend(loc="upper right", fontsize=8)
    for j in range(res.u.shape[1]):
        axs[1].step(t, res.u[:, j], where="post", lw=1.2, label=f"$u_{j + 1}$" if res.u.shape[1] > 1 else "$u$")
    axs[1].set_ylabel("input $u$")
    E = np.maximum(res.E_enc, 1e-300)
    axs[2].semilogy(t, E, lw=1.2, color="C3", label="encoder")
    E_dec = getattr(res, "E_dec", None)
    if E_dec is not None and np.any(np.isfinite(E_dec)):
        axs[2].semilogy(t, np.maximum(E_dec, 1e-300), lw=1.0, ls="--", color="k", label="decoder")
        axs[2].legend(loc="upper right", fontsize=8)
    axs[2].set_ylabel("range $E_k$")
    axs[2].set_xlabel("time $t$ [s]")
    for ax in axs:
        for a, b in spans:
            ax.axvspan(a, b if b > a else a + 0.02 * res.T, color="0.6", alpha=0.35, lw=0)
        ax.grid(alpha=0.3)
    if title:
        axs[0].set_title(title)
    return _save(fig, path)


def plot_phase_portrait(roa, path, *, trajectories=(), vulnerable=None, baseline=None, title: str = "",
                        labels=("$x_1$", "$x_2$"), zoom=None):
    """Nominal region of attraction (gray) with trajectories (paper, Fig. 3).

    Parameters
    ----------
    roa : a :class:`testbed.analysis.roa.RoaResult`.
    trajectories : iterable of (label, X (N, n) states, matplotlib color).
    vulnerable : optional :class:`testbed.analysis.sweep.VulnerableResult` drawn on top
        (red: the attacker makes the loop fail from there).
    baseline : optional VulnerableResult without attack (zero budget): the states the
        quantized loop loses by itself are drawn dark, the ones lost to the attack red.
    zoom : optional half-widths (wx, wy): a second panel around the origin.
    """
    plt = _plt()
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    panels = 2 if zoom is not None else 1
    fig, axs = plt.subplots(1, panels, figsize=(6.2 * panels, 5.8), squeeze=False, layout="constrained")
    ext = [roa.xs[0], roa.xs[-1], roa.ys[0], roa.ys[-1]]
    d0, d1 = roa.dims
    for k, ax in enumerate(axs[0]):
        ax.imshow(roa.inside.astype(float), origin="lower", extent=ext, aspect="auto",
                  cmap=ListedColormap(["white", "0.75"]), vmin=0, vmax=1, interpolation="nearest")
        if vulnerable is not None:
            fail = vulnerable.outcome >= 1
            base = (baseline.outcome >= 1) if baseline is not None else np.zeros_like(fail)
            vext = [vulnerable.xs[0], vulnerable.xs[-1], vulnerable.ys[0], vulnerable.ys[-1]]
            dx = (vext[1] - vext[0]) / max(len(vulnerable.xs) - 1, 1) / 2
            dy = (vext[3] - vext[2]) / max(len(vulnerable.ys) - 1, 1) / 2
            vext = [vext[0] - dx, vext[1] + dx, vext[2] - dy, vext[3] + dy]
            layer = np.where(base, 2.0, np.where(fail, 1.0, np.nan))
            ax.imshow(np.ma.masked_invalid(layer), origin="lower", extent=vext, aspect="auto",
                      cmap=ListedColormap(["#d62728", "#4a0d0d"]), vmin=1, vmax=2, alpha=0.8,
                      interpolation="nearest")
        for label, X, color in trajectories:
            X = np.asarray(X)
            ax.plot(X[:, d0], X[:, d1], lw=1.1, color=color, label=label, marker="." if k else None, ms=2)
            ax.plot(X[0, d0], X[0, d1], "o", color=color, ms=4)
        if k == 0:
            ax.set_xlim(ext[0], ext[1])
            ax.set_ylim(ext[2], ext[3])
        else:
            c = roa.center
            ax.set_xlim(c[d0] - zoom[0], c[d0] + zoom[0])
            ax.set_ylim(c[d1] - zoom[1], c[d1] + zoom[1])
            ax.set_title("zoom near the origin")
        ax.set_xlabel(labels[0])
        ax.set_ylabel(labels[1])
        ax.grid(alpha=0.25)
    ax = axs[0][0]
    handles, _ = ax.get_legend_handles_labels()
    handles.append(Patch(color="0.75", label="nominal region of attraction"))
    if baseline is not None:
        handles.append(Patch(color="#4a0d0d", alpha=0.8, label="lost without any attack (quantization)"))
    if vulnerable is not None:
        kF, rF, kD, rD = vulnerable.budget
        handles.append(Patch(color="#d62728", alpha=0.8,
                             label=f"fails under {vulnerable.kind} DoS ($\\kappa_F$={kF:g}, $\\rho_F$={rF:g}, "
                                   f"$\\kappa_D$={kD:g}, $\\rho_D$={rD:g})"))
    ax.legend(handles=handles, loc="upper right", fontsize=7)
    if title:
        ax.set_title(title)
    return _save(fig, path)


def plot_allowable_region(path, *, regions=None, plain=None, sweep=None, budget=None, title: str = "",
                          zoom: bool = True, sweep_zoom=None):
    """Theorem 1 boundaries over the empirical map (paper, Fig. 4, plus the sweep).

    Parameters
    ----------
    regions : dict rule -> :class:`testbed.analysis.theorem1.Region`.
    plain : the plain :class:`Certificate` (its triangle is drawn dashed).
    sweep : :class:`testbed.analysis.sweep.SweepResult` (worst-case converged fraction
        as background, the empirical boundary per kind as lines).
    budget : (kappa_F, rho_F, kappa_D, rho_D) to mark.
    zoom : add a second panel zoomed on the theoretical region.
    sweep_zoom : a finer sweep over the zoomed window, shown as its background.
    """
    plt = _plt()
    panels = 2 if (zoom and sweep is not None) else 1
    fig, axs = plt.subplots(1, panels, figsize=(6.4 * panels, 5.2), squeeze=False, layout="constrained")
    axs = axs[0]
    styles = {"paper": ("C0", "-", "Theorem 1, optimized $P_p$, $\\varphi_p$ ((mu0),(mu1))"),
              "tight": ("C2", "-.", "Theorem 1, optimized, smallest $\\mu$ of (mu)")}
    def background(ax, sw):
        W = sw.worst()
        dF = np.diff(sw.rho_F).mean() if len(sw.rho_F) > 1 else 1.0
        dD = np.diff(sw.rho_D).mean() if len(sw.rho_D) > 1 else 1.0
        ext = [sw.rho_D[0] - dD / 2, sw.rho_D[-1] + dD / 2, sw.rho_F[0] - dF / 2, sw.rho_F[-1] + dF / 2]
        im = ax.imshow(np.nan_to_num(W, nan=1.0), origin="lower", extent=ext, aspect="auto", cmap="RdYlGn",
                       vmin=0, vmax=1, interpolation="nearest", alpha=0.85)
        return im, ext

    for k, ax in enumerate(axs):
        if sweep is not None and k == 0:
            im, ext = background(ax, sweep)
            cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02)
            cb.set_label("converged fraction (worst attacker kind)")
            for kind, color in zip(sweep.kinds, ("k", "C4", "C3")):
                eb = sweep.empirical_boundary(kind)
                ax.plot(sweep.rho_D, eb, color=color, lw=1.4, ls=":", marker=".", ms=4,
                        label=f"empirical: all {kind} runs converge below")
        if sweep_zoom is not None and k == 1:
            background(ax, sweep_zoom)
        if regions:
            for rule, reg in regions.items():
                c, ls, lab = styles.get(rule, ("C1", "-", rule))
                ax.plot(reg.rho_D, reg.rho_F, color=c, ls=ls, lw=2.0, label=lab)
        if plain is not None:
            rd = np.linspace(0, plain.rho_D_max, 50)
            ax.plot(rd, plain.boundary(rd), color="C1", ls="--", lw=1.6, label="Theorem 1, plain choice (dlyap, I)")
        if budget is not None:
            ax.plot(budget[3], budget[1], "k*", ms=10, label="scenario budget")
        ax.set_xlabel("$\\rho_D$ (average DoS duration)")
        ax.set_ylabel("$\\rho_F$ (average DoS frequency) [1/s]")
        ax.grid(alpha=0.3)
        if k == 1 or sweep is None:
            hi_d = max((r.rho_D_max for r in (regions or {}).values()), default=0.05) * 1.15
            hi_f = max((r.rho_F_max for r in (regions or {}).values()), default=0.5) * 1.15
            if sweep is not None and sweep_zoom is None:
                RD, RF = np.meshgrid(sweep.rho_D, sweep.rho_F)
                sel = (RD <= hi_d) & (RF <= hi_f)
                ax.scatter(RD[sel], RF[sel], c=np.nan_to_num(sweep.worst(), nan=1.0)[sel], cmap="RdYlGn", vmin=0,
                           vmax=1, s=70, marker="s", edgecolors="k", linewidths=0.4, zorder=3,
                           label="sweep points (worst converged fraction)")
                ax.legend(loc="upper right", fontsize=7)
            ax.set_xlim(0, hi_d)
            ax.set_ylim(0, hi_f)
            if k == 1:
                ax.set_title("zoom on Theorem 1's region" + (" (finer sweep behind)" if sweep_zoom else ""))
                ax.legend(loc="upper right", fontsize=7)
        else:
            ax.set_xlim(ext[0], ext[1])
            ax.set_ylim(ext[2], ext[3])
    axs[0].legend(loc="upper right", fontsize=7, framealpha=0.9)
    if title:
        axs[0].set_title(title)
    return _save(fig, path)


def plot_delta(rows, path, *, gamma_mark=None, delta_paper=None, title: str = ""):
    """delta(gamma) of Lemma 2 (and E0 bounds if present) on log-log axes.

    rows : list of dicts with "gamma", "delta" (and optionally "E0_bound").
    """
    plt = _plt()
    g = np.array([r["gamma"] for r in rows])
    d = np.array([r["delta"] if r["delta"] is not None else np.nan for r in rows])
    fig, ax = plt.subplots(figsize=(6.0, 4.2))
    ax.loglog(g, d, "C0-", label="$\\delta$ (Lemma 2)")
    if any("E0_bound" in r for r in rows):
        e = np.array([r.get("E0_bound") or np.nan for r in rows])
        ax.loglog(g, e, "C3--", label="$E_0$ bound (Theorem 2)")
    if delta_paper is not None:
        ax.axhline(delta_paper, color="0.4", ls=":", label=f"paper: $\\delta$ = {delta_paper:g}")
    if gamma_mark is not None:
        ax.axvline(gamma_mark, color="C2", ls=":", label=f"chosen $\\gamma$ = {gamma_mark:.3g}")
    ax.set_xlabel("$\\gamma$")
    ax.set_ylabel("radius")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title)
    return _save(fig, path)


def plot_vulnerability(vm, roa, path, *, title: str = "", labels=("$x_1$", "$x_2$"), x0=None,
                       show: str = "duration"):
    """Heat map of the least DoS duration that defeats the loop, over the nominal region of attraction.

    Parameters
    ----------
    vm : a :class:`testbed.analysis.worst.VulnerabilityMap`.
    roa : the :class:`testbed.analysis.roa.RoaResult` it was computed on (its outline is drawn).
    x0 : optional initial state to mark.
    show : "duration" (the least total duration of at most ``vm.attacks`` attacks) or "samples"
        (the fewest lost samples S*).
    Theorem 2's delta-ball ||x||_inf <= delta (``vm.delta``) is drawn around the origin, with an
    inset when it is too small to see.
    """
    plt = _plt()
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch, Rectangle

    fig, ax = plt.subplots(figsize=(7.0, 5.8), layout="constrained")
    dx = (vm.xs[-1] - vm.xs[0]) / max(len(vm.xs) - 1, 1) / 2
    dy = (vm.ys[-1] - vm.ys[0]) / max(len(vm.ys) - 1, 1) / 2
    ext = [vm.xs[0] - dx, vm.xs[-1] + dx, vm.ys[0] - dy, vm.ys[-1] + dy]
    heat = np.where(vm.samples > 0, vm.samples if show == "samples" else vm.duration, np.nan)
    im = ax.imshow(np.ma.masked_invalid(heat), origin="lower", extent=ext, aspect="auto", cmap="viridis",
                   interpolation="nearest")
    cb = fig.colorbar(im, ax=ax)
    cb.set_label("fewest lost samples that make the loop escape" if show == "samples" else
                 "least total DoS duration that makes the loop escape [s]")
    lost = np.where(vm.samples == 0, 1.0, np.nan)
    ax.imshow(np.ma.masked_invalid(lost), origin="lower", extent=ext, aspect="auto",
              cmap=ListedColormap(["black"]), vmin=0, vmax=1, interpolation="nearest")
    none = np.where(vm.samples == -1, 1.0, np.nan)
    ax.imshow(np.ma.masked_invalid(none), origin="lower", extent=ext, aspect="auto",
              cmap=ListedColormap(["#f0c0c0"]), vmin=0, vmax=1, interpolation="nearest")
    d0, d1 = roa.dims
    ax.contour(roa.xs, roa.ys, roa.inside.astype(float), levels=[0.5], colors="0.2", linewidths=1.0)
    c = roa.center
    handles = [Patch(facecolor="none", edgecolor="0.2", label="nominal region of attraction (outline)"),
               Patch(color="black", label="escapes without any attack (quantization)")]
    if np.any(vm.samples == -1):
        handles.append(Patch(color="#f0c0c0", label=f"no escape with attacks up to {vm.max_len} samples"))
    if vm.delta is not None and np.isfinite(vm.delta) and vm.delta > 0:
        dl = float(vm.delta)
        ax.add_patch(Rectangle((c[d0] - dl, c[d1] - dl), 2 * dl, 2 * dl, fill=False, ec="red", lw=1.2))
        ax.plot([c[d0]], [c[d1]], "+", color="red", ms=8)
        handles.append(Patch(facecolor="none", edgecolor="red",
                             label=f"Theorem 2: $\\|x\\|_\\infty \\leq \\delta$ = {dl:.3g}"))
        if 2 * dl < 0.05 * (ext[1] - ext[0]):
            ins = ax.inset_axes([0.04, 0.04, 0.28, 0.28])
            ins.imshow(np.ma.masked_invalid(heat), origin="lower", extent=ext, aspect="auto", cmap="viridis",
                       norm=im.norm, interpolation="nearest")
            ins.add_patch(Rectangle((c[d0] - dl, c[d1] - dl), 2 * dl, 2 * dl, fill=False, ec="red", lw=1.2))
            w = max(4 * dl, 3 * dx)
            ins.set_xlim(c[d0] - w, c[d0] + w)
            ins.set_ylim(c[d1] - w, c[d1] + w)
            ins.set_xticks([])
            ins.set_yticks([])
            ins.set_title("near the origin", fontsize=7)
    if x0 is not None:
        x0 = np.asarray(x0, dtype=float)
        ax.plot([x0[d0]], [x0[d1]], "o", mfc="none", mec="white", ms=7)
    ax.set_xlim(ext[0], ext[1])
    ax.set_ylim(ext[2], ext[3])
    ax.set_xlabel(labels[0])
    ax.set_ylabel(labels[1])
    ax.legend(handles=handles, loc="upper right", fontsize=7)
    kind = "one attack" if vm.attacks == 1 else f"at most {vm.attacks} attacks"
    ax.set_title(title or f"least DoS duration ({kind}) that defeats the loop")
    return _save(fig, path)
