"""The figures of the testbed (matplotlib, Agg backend, imported lazily), in the style of
``testbed.common.figstyle`` (sizes, formats by extension, palette, DoS shading, legends outside the data).

* :func:`plot_time_series`: x_k, u_k and E_k over time with the DoS intervals
  shaded (the paper's second figure);
* :func:`plot_phase_portrait`: the nominal region of attraction (gray), trajectories
  (the scenario's, and others the command names), optionally the vulnerable states of a budget (the third figure);
* :func:`plot_allowable_region`: Theorem 1's boundary in the (rho_D, rho_F) plane
  for the plain, optimized and tight choices over the empirical convergence map
  of a sweep (the fourth figure, plus the experiment);
* :func:`plot_compare`: two runs A and B (``testbed compare``): states (one hue per component,
  A solid, B dashed), their difference, the lost samples of each, DoS shaded;
* :func:`plot_delta`: delta (Lemma 2) and the E_0 bound (Theorem 2) against gamma;
* :func:`plot_vulnerability`: the least DoS duration that defeats the loop over the region of
  attraction, with Theorem 2's delta-ball (the figure the paper's conclusion asks for).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any

import numpy as np

from ..common import figstyle

if TYPE_CHECKING:
    import numpy.typing as npt
    from matplotlib.artist import Artist

    from ..scenario import Scenario
    from .roa import RoaResult


def _plt():
    return figstyle.pyplot()


def dos_spans(theta: npt.ArrayLike | None, T: float,
              intervals: Iterable[Sequence[float]] | None = None) -> list[tuple[float, float]]:
    """Time spans to shade: the attack intervals if given, else [t_k, t_{k+1}) over runs of theta_k = 1."""
    if intervals is not None:
        return [(a, a + max(tau, 0.0)) for a, tau in intervals]
    th = np.asarray(theta).astype(bool)
    if not th.any():
        return []
    d = np.diff(np.concatenate(([0], th.astype(np.int8), [0])))
    starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    return [(s * T, e * T) for s, e in zip(starts, ends)]


def figure_title(sc: Scenario) -> str:
    """The title of a run's time-series figure: the scenario and its initial state (mathtext)."""
    return f"{sc.name}: $x_0$ = {[float(f'{v:.4g}') for v in sc.x0]}"


def series_of_run(run: Any) -> SimpleNamespace:  # run: a testbed.Run (a layer above)
    """What :func:`plot_time_series` reads, from a ``testbed.runs.run.Run`` (its arrays)."""
    a = run.arrays
    return SimpleNamespace(T=run.scenario.T, t=np.asarray(a["t"], float), x=np.asarray(a["x"], float),
                           u=np.asarray(a["u"], float), E_enc=np.asarray(a["E"], float),
                           E_dec=np.asarray(a["E_dec"], float), theta=np.asarray(a["theta"]).astype(int))


def plot_time_series(res: Any, path: str | Path, *, title: str = "", intervals: Iterable[Sequence[float]] | None = None,
                     size: str = "page") -> Path:
    """States, input and quantizer range E_k against time, DoS shaded (paper, Fig. 2).

    Parameters
    ----------
    res : a ``testbed.sim.loop.SimResult`` (or anything with ``T, t, x, u, E_enc, E_dec, theta``;
        :func:`series_of_run` makes one of a ``Run``).
    intervals : attack intervals [(a_i, tau_i), ...] to shade (default: runs of lost samples).
    size : ``"column"`` or ``"page"`` (``testbed.common.figstyle``).
    """
    spans = dos_spans(res.theta, res.T, intervals)
    with figstyle.style(size):
        fig, axs = figstyle.subplots(size, 3, 1, aspect=0.25 if size == "page" else 0.42, sharex=True)
        axs = axs[:, 0]
        t = res.t
        n = res.x.shape[1]
        for i in range(n):
            axs[0].plot(t, res.x[:, i], label=f"$x_{{{i + 1}}}$")
        axs[0].set_ylabel("state $x$")
        m = res.u.shape[1]
        for j in range(m):
            axs[1].step(t, res.u[:, j], where="post", color=figstyle.CYCLE[(n + j) % len(figstyle.CYCLE)],
                        label=f"$u_{{{j + 1}}}$" if m > 1 else "$u$")
        axs[1].set_ylabel("input $u$")
        E = np.maximum(res.E_enc, 1e-300)
        axs[2].semilogy(t, E, color=figstyle.BLACK, label="$E_k$, encoder")
        E_dec = getattr(res, "E_dec", None)
        if E_dec is not None and np.any(np.isfinite(E_dec)):
            axs[2].semilogy(t, np.maximum(E_dec, 1e-300), ls="--", color=figstyle.ORANGE, label="$E_k$, decoder")
        axs[2].set_ylabel("range $E_k$")
        axs[2].set_xlabel("time $t$ [s]")
        for ax in axs:
            figstyle.shade_dos(ax, spans, T=res.T)
        axs[0].set_xlim(t[0] if len(t) else 0, (t[-1] + res.T) if len(t) else 1)
        if title:
            axs[0].set_title(title)
        figstyle.legend_below(fig, axes=axs, ncol=min(n + m + 3, 7 if size == "page" else 4))
        return figstyle.save(fig, path)


def _square(size: str, nr: int, nc: int) -> float:
    """The ``aspect`` of ``figstyle.subplots`` for about square panels (legend below included)."""
    if nr * nc == 1:
        return 0.85 if size == "column" else 0.6
    return 0.85 if size == "column" else 0.95


def plot_phase_portrait(roa: RoaResult, path: str | Path, *, trajectories: Iterable[Any] = (), vulnerable: Any = None,
                        baseline: Any = None, title: str = "", labels: tuple[str, str] = ("$x_1$", "$x_2$"),
                        zoom: Any = None, size: str = "page") -> Path:
    """Nominal region of attraction (gray) with trajectories (paper, Fig. 3).

    Parameters
    ----------
    roa : a :class:`testbed.analysis.roa.RoaResult`.
    trajectories : iterable of (label, X (N, n) states, color); ``color`` None takes the palette's next.
    vulnerable : optional :class:`testbed.analysis.sweep.VulnerableResult` drawn on top
        (the attacker makes the loop fail from there).
    baseline : optional VulnerableResult without attack (zero budget): the states the
        quantized loop loses by itself are drawn dark, the ones lost to the attack in vermillion.
    zoom : optional half-widths (wx, wy): a second panel around the origin.
    """
    from matplotlib.colors import ListedColormap
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    lost_attack, lost_alone = figstyle.VERMILLION, "#3b1a00"
    with figstyle.style(size):
        nr, nc = figstyle.panels(size, 2 if zoom is not None else 1)
        fig, axs = figstyle.subplots(size, nr, nc, aspect=_square(size, nr, nc))
        axs = axs.ravel()
        ext = [roa.xs[0], roa.xs[-1], roa.ys[0], roa.ys[-1]]
        d0, d1 = roa.dims
        handles: list[Artist] = []
        for k, ax in enumerate(axs):
            ax.imshow(roa.inside.astype(float), origin="lower", extent=ext, aspect="auto",
                      cmap=ListedColormap(["white", "0.8"]), vmin=0, vmax=1, interpolation="nearest")
            if vulnerable is not None:
                fail = vulnerable.outcome >= 1
                base = (baseline.outcome >= 1) if baseline is not None else np.zeros_like(fail)
                vext = [vulnerable.xs[0], vulnerable.xs[-1], vulnerable.ys[0], vulnerable.ys[-1]]
                dx = (vext[1] - vext[0]) / max(len(vulnerable.xs) - 1, 1) / 2
                dy = (vext[3] - vext[2]) / max(len(vulnerable.ys) - 1, 1) / 2
                vext = [vext[0] - dx, vext[1] + dx, vext[2] - dy, vext[3] + dy]
                layer = np.where(base, 2.0, np.where(fail, 1.0, np.nan))
                ax.imshow(np.ma.masked_invalid(layer), origin="lower", extent=vext, aspect="auto",
                          cmap=ListedColormap([lost_attack, lost_alone]), vmin=1, vmax=2, alpha=0.85,
                          interpolation="nearest")
            for i, (label, X, color) in enumerate(trajectories):
                X = np.asarray(X)
                color = color or figstyle.CYCLE[i % len(figstyle.CYCLE)]
                ax.plot(X[:, d0], X[:, d1], color=color, marker="." if k else None, ms=2, label=label)
                ax.plot(X[0, d0], X[0, d1], "o", color=color, ms=4)
                if k == 0:
                    handles.append(Line2D([], [], color=color, marker="o", ms=3, label=label))
            if k == 0:
                ax.set_xlim(ext[0], ext[1])
                ax.set_ylim(ext[2], ext[3])
            else:
                c = roa.center
                ax.set_xlim(c[d0] - zoom[0], c[d0] + zoom[0])
                ax.set_ylim(c[d1] - zoom[1], c[d1] + zoom[1])
                ax.set_title("near the origin")
            ax.set_xlabel(labels[0])
            ax.set_ylabel(labels[1])
        handles.append(Patch(color="0.8", label="nominal region of attraction"))
        if baseline is not None:
            handles.append(Patch(color=lost_alone, alpha=0.85, label="lost without any attack (quantization)"))
        if vulnerable is not None:
            kF, rF, kD, rD = vulnerable.budget
            handles.append(Patch(color=lost_attack, alpha=0.85,
                                 label=f"fails under {vulnerable.kind} DoS ($\\kappa_F$ = {kF:g}, $\\rho_F$ = {rF:g}, "
                                       f"$\\kappa_D$ = {kD:g}, $\\rho_D$ = {rD:g})"))
        if title:
            axs[0].set_title(title)
        figstyle.legend_below(fig, handles, ncol=1 if size == "column" else 2)
        return figstyle.save(fig, path)


#: legend labels and styles of Theorem 1's boundaries (rule -> color, line style, label)
THEOREM1_STYLES = {
    "paper": (figstyle.BLUE, "-", "Theorem 1: optimized $P_p$, $\\varphi_p$; the paper's $\\mu_0$, $\\mu_1$"),
    "tight": (figstyle.GREEN, "-.", "Theorem 1: optimized $P_p$, $\\varphi_p$; smallest $\\mu_0$, $\\mu_1$"),
    "plain": (figstyle.BLACK, "--", "Theorem 1: plain choice ($P_p$ by dlyap with $I$)"),
}
#: empirical boundary per attacker kind: color, marker, line style
KIND_STYLES = {"random": (figstyle.VERMILLION, "o", "-"), "periodic": (figstyle.SKY, "s", "--"),
               "greedy": (figstyle.PURPLE, "^", ":")}


def plot_allowable_region(path: str | Path, *, regions: Any = None, plain: Any = None, sweep: Any = None,
                          budget: Sequence[float] | None = None, budget_label: str | None = None,
                          title: str = "", zoom: bool = True, sweep_zoom: Any = None, size: str = "page") -> Path:
    """Theorem 1 boundaries, over the empirical map of a sweep when there is one (paper, Fig. 4).

    Parameters
    ----------
    regions : dict rule -> :class:`testbed.analysis.region.Region`.
    plain : the plain :class:`Certificate` (its triangle is drawn dashed).
    sweep : :class:`testbed.analysis.sweep.SweepResult` (worst-case converged fraction
        as background, the empirical boundary per kind as lines).
    budget : (kappa_F, rho_F, kappa_D, rho_D) to mark, named ``budget_label`` in the legend.
    zoom : add a second panel zoomed on the theoretical region (with a sweep only).
    sweep_zoom : a finer sweep over the zoomed window, shown as its background.
    """

    n_panels = 2 if (zoom and sweep is not None) else 1
    with figstyle.style(size):
        nr, nc = figstyle.panels(size, n_panels)
        aspect = _square(size, nr, nc) * (1.35 if (size == "page" and n_panels == 2) else 1.0)
        fig, axs = figstyle.subplots(size, nr, nc, aspect=aspect)
        axs = axs.ravel()

        def background(ax, sw):
            W = sw.worst()
            dF = np.diff(sw.rho_F).mean() if len(sw.rho_F) > 1 else 1.0
            dD = np.diff(sw.rho_D).mean() if len(sw.rho_D) > 1 else 1.0
            ext = [sw.rho_D[0] - dD / 2, sw.rho_D[-1] + dD / 2, sw.rho_F[0] - dF / 2, sw.rho_F[-1] + dF / 2]
            im = ax.imshow(np.nan_to_num(W, nan=1.0), origin="lower", extent=ext, aspect="auto",
                           cmap=figstyle.CMAP, vmin=0, vmax=1, interpolation="nearest")
            return im, ext

        hi_d = max((r.rho_D_max for r in (regions or {}).values()), default=0.05) * 1.15
        hi_f = max((r.rho_F_max for r in (regions or {}).values()), default=0.5) * 1.15
        if budget is not None:
            hi_d, hi_f = max(hi_d, budget[3] * 1.15), max(hi_f, budget[1] * 1.15)
        for k, ax in enumerate(axs):
            ext = None
            if sweep is not None and k == 0:
                im, ext = background(ax, sweep)
                cb = fig.colorbar(im, ax=axs if size == "column" else axs[0], location="right", fraction=0.05,
                                  pad=0.02)
                cb.set_label("converged fraction (worst attacker kind)")
                for kind in sweep.kinds:
                    color, marker, ls = KIND_STYLES.get(kind, (figstyle.BLACK, "x", "-"))
                    ax.plot(sweep.rho_D, sweep.empirical_boundary(kind), color=color, ls=ls, marker=marker, ms=3,
                            mec="white", mew=0.4, label=f"empirical: every {kind} run converges below")
            if sweep_zoom is not None and k == 1:
                _, ext = background(ax, sweep_zoom)
            for rule, reg in (regions or {}).items():
                c, ls, lab = THEOREM1_STYLES.get(rule, (figstyle.ORANGE, "-", rule))
                ax.plot(reg.rho_D, reg.rho_F, color=c, ls=ls, lw=1.6, label=lab)
            if plain is not None:
                rd = np.linspace(0, plain.rho_D_max, 50)
                c, ls, lab = THEOREM1_STYLES["plain"]
                ax.plot(rd, plain.boundary(rd), color=c, ls=ls, lw=1.3, label=lab)
            if budget is not None:
                ax.plot(budget[3], budget[1], "*", color=figstyle.ORANGE, mec="black", mew=0.5, ms=9, clip_on=False,
                        zorder=5, label=budget_label or "the scenario's budget")
            ax.set_xlabel("$\\rho_D$ (average DoS duration)")
            ax.set_ylabel("$\\rho_F$ (average DoS frequency) [1/s]")
            if sweep is None or k == 1:
                pad_d, pad_f = 0.04 * hi_d, 0.04 * hi_f
                if sweep is not None and sweep_zoom is None:
                    RD, RF = np.meshgrid(sweep.rho_D, sweep.rho_F)
                    sel = (RD <= hi_d) & (RF <= hi_f)
                    ax.scatter(RD[sel], RF[sel], c=np.nan_to_num(sweep.worst(), nan=1.0)[sel], cmap=figstyle.CMAP,
                               vmin=0, vmax=1, s=40, marker="s", edgecolors="k", linewidths=0.4, zorder=3,
                               clip_on=False, label="sweep points (worst converged fraction)")
                    pad_d, pad_f = 0.06 * hi_d, 0.06 * hi_f
                ax.set_xlim(-pad_d, hi_d + pad_d)
                ax.set_ylim(-pad_f, hi_f + pad_f)
                if k == 1:
                    ax.set_title("zoom on Theorem 1's region" + (", finer sweep" if sweep_zoom else ""))
            else:
                assert ext is not None  # the first panel of a sweep: its background's extent
                ax.set_xlim(ext[0], ext[1])
                ax.set_ylim(ext[2], ext[3])
        if title and n_panels > 1:
            fig.suptitle(title)
        elif title:
            axs[0].set_title(title)
        handles: list[Artist] = []
        seen = set()
        for ax in axs:
            for h, lab in zip(*ax.get_legend_handles_labels()):
                if lab not in seen:
                    seen.add(lab)
                    handles.append(h)
        figstyle.legend_below(fig, handles, ncol=1 if size == "column" else 2)
        return figstyle.save(fig, path)


def plot_delta(rows: Sequence[dict], path: str | Path, *, gamma_mark: float | None = None,
               E0_mark: float | None = None, delta_paper: float | None = None, title: str = "",
               size: str = "page") -> Path:
    """delta(gamma) of Lemma 2 (and E0 bounds if present) on log-log axes.

    rows : list of dicts with "gamma", "delta" (and optionally "E0_bound"; None where Theorem 2's
        conditions fail: the curve stops there, and the legend says so).
    gamma_mark, E0_mark : the chosen gamma and its E0 bound (a point on the curve).
    """
    g = np.array([r["gamma"] for r in rows])
    d = np.array([r["delta"] if r["delta"] is not None else np.nan for r in rows])
    with figstyle.style(size):
        fig, axs = figstyle.subplots(size, aspect=0.62 if size == "column" else 0.42)
        ax = axs[0, 0]
        ax.loglog(g, d, color=figstyle.BLUE, marker="o", ms=2.5, label="$\\delta$ (Lemma 2)")
        if any("E0_bound" in r for r in rows):
            e = np.array([r.get("E0_bound") or np.nan for r in rows])
            lab = "$E_0$ bound (Theorem 2)"
            if np.isnan(e).any() and np.isfinite(e).any():
                stop = g[np.isfinite(e)].max()
                lab += f"; none above $\\gamma$ = {stop:.3g} on this grid (its conditions fail)"
            ax.loglog(g, e, color=figstyle.VERMILLION, ls="--", marker="s", ms=2.5, label=lab)
            if gamma_mark is not None and E0_mark is not None and np.isfinite(E0_mark):
                ax.loglog([gamma_mark], [E0_mark], "D", color=figstyle.VERMILLION, ms=4,
                          label=f"$E_0$ bound at the chosen $\\gamma$: {E0_mark:.3g}")
        if delta_paper is not None:
            ax.axhline(delta_paper, color="0.4", ls=":", label=f"the paper's $\\delta$ = {delta_paper:g}")
        if gamma_mark is not None:
            ax.axvline(gamma_mark, color=figstyle.GREEN, ls="-.", label=f"chosen $\\gamma$ = {gamma_mark:.3g}")
        ax.set_xlabel("$\\gamma$")
        ax.set_ylabel("radius")
        ax.grid(alpha=0.3, which="both")
        if title:
            ax.set_title(title)
        figstyle.legend_below(fig, ncol=1 if size == "column" else 2)
        return figstyle.save(fig, path)


def plot_vulnerability(vm: Any, roa: RoaResult, path: str | Path, *, title: str = "",
                       labels: tuple[str, str] = ("$x_1$", "$x_2$"), x0: npt.ArrayLike | None = None,
                       show: str = "duration", size: str = "page") -> Path:
    """Heat map of the least DoS duration that defeats the loop, over the nominal region of attraction.

    Parameters
    ----------
    vm : a :class:`testbed.analysis.vulnerability.VulnerabilityMap`.
    roa : the :class:`testbed.analysis.roa.RoaResult` it was computed on (its outline is drawn).
    x0 : optional initial state to mark.
    show : "duration" (the least total duration of at most ``vm.attacks`` attacks) or "samples"
        (the fewest lost samples S*).
    Theorem 2's delta-ball ||x||_inf <= delta (``vm.delta``) is drawn around the origin, with an
    inset when it is too small to see.
    """
    from matplotlib.colors import ListedColormap
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch, Rectangle

    with figstyle.style(size):
        fig, axs = figstyle.subplots(size, aspect=0.95 if size == "column" else 0.62)
        ax = axs[0, 0]
        dx = (vm.xs[-1] - vm.xs[0]) / max(len(vm.xs) - 1, 1) / 2
        dy = (vm.ys[-1] - vm.ys[0]) / max(len(vm.ys) - 1, 1) / 2
        ext = [vm.xs[0] - dx, vm.xs[-1] + dx, vm.ys[0] - dy, vm.ys[-1] + dy]
        heat = np.where(vm.samples > 0, vm.samples if show == "samples" else vm.duration, np.nan)
        im = ax.imshow(np.ma.masked_invalid(heat), origin="lower", extent=ext, aspect="auto", cmap=figstyle.CMAP,
                       interpolation="nearest")
        cb = fig.colorbar(im, ax=ax)
        cb.set_label("fewest lost samples that make the loop escape" if show == "samples" else
                     "least total DoS duration to escape [s]")
        lost = np.where(vm.samples == 0, 1.0, np.nan)
        ax.imshow(np.ma.masked_invalid(lost), origin="lower", extent=ext, aspect="auto",
                  cmap=ListedColormap(["black"]), vmin=0, vmax=1, interpolation="nearest")
        none = np.where(vm.samples == -1, 1.0, np.nan)
        ax.imshow(np.ma.masked_invalid(none), origin="lower", extent=ext, aspect="auto",
                  cmap=ListedColormap([figstyle.SKY]), vmin=0, vmax=1, interpolation="nearest")
        d0, d1 = roa.dims
        ax.contour(roa.xs, roa.ys, roa.inside.astype(float), levels=[0.5], colors="0.2", linewidths=1.0)
        c = roa.center
        handles: list[Artist] = [
            Patch(facecolor="none", edgecolor="0.2", label="nominal region of attraction (outline)"),
            Patch(color="black", label="escapes without any attack (quantization)")]
        if np.any(vm.samples == -1):
            handles.append(Patch(color=figstyle.SKY, label=f"no escape with attacks up to {vm.max_len} samples"))
        if vm.delta is not None and np.isfinite(vm.delta) and vm.delta > 0:
            dl = float(vm.delta)
            red = figstyle.VERMILLION
            ax.add_patch(Rectangle((c[d0] - dl, c[d1] - dl), 2 * dl, 2 * dl, fill=False, ec=red, lw=1.2))
            ax.plot([c[d0]], [c[d1]], "+", color=red, ms=8)
            handles.append(Patch(facecolor="none", edgecolor=red,
                                 label=f"Theorem 2: $\\|x\\|_\\infty \\leq \\delta$ = {dl:.3g}"))
            if 2 * dl < 0.05 * (ext[1] - ext[0]):
                ins = ax.inset_axes([0.04, 0.04, 0.28, 0.28])
                ins.imshow(np.ma.masked_invalid(heat), origin="lower", extent=ext, aspect="auto", cmap=figstyle.CMAP,
                           norm=im.norm, interpolation="nearest")
                ins.add_patch(Rectangle((c[d0] - dl, c[d1] - dl), 2 * dl, 2 * dl, fill=False, ec=red, lw=1.2))
                w = max(4 * dl, 3 * dx)
                ins.set_xlim(c[d0] - w, c[d0] + w)
                ins.set_ylim(c[d1] - w, c[d1] + w)
                ins.set_xticks([])
                ins.set_yticks([])
                ins.grid(False)
                ins.set_title("near the origin", fontsize=6)
        if x0 is not None:
            x0 = np.asarray(x0, dtype=float)
            ax.plot([x0[d0]], [x0[d1]], "o", mfc="none", mec="white", ms=7)
            handles.append(Line2D([], [], ls="", marker="o", mfc="none", mec="0.3", ms=6,
                                  label=f"the scenario's $x_0$ = {np.round(x0, 4).tolist()}"))
        ax.set_xlim(ext[0], ext[1])
        ax.set_ylim(ext[2], ext[3])
        ax.set_xlabel(labels[0])
        ax.set_ylabel(labels[1])
        ax.grid(False)
        kind = "one attack" if vm.attacks == 1 else f"at most {vm.attacks} attacks"
        what = "fewest lost samples" if show == "samples" else "least DoS duration"
        ax.set_title(title or f"{what} ({kind}) that defeats the loop")
        figstyle.legend_below(fig, handles, ncol=1 if size == "column" else 2)
        return figstyle.save(fig, path)


def _run_spans(run) -> list[tuple[float, float]]:
    """A ``Run``'s DoS intervals as (start, end): its realized intervals, else runs of attack_on."""
    ivs = (run.summary or {}).get("dos_intervals")
    if ivs is not None:
        return dos_spans(None, run.scenario.T, ivs)
    return dos_spans(run.arrays["attack_on"], run.scenario.T)


def plot_compare(a_run: Any, b_run: Any, path: str | Path, *, names: tuple[str, str] = ("A", "B"), title: str = "",
                 size: str = "page") -> Path:
    """Two runs over time: x of both (component i in one hue, A solid, B dashed), ||x_A - x_B||_inf
    on a log scale, and the lost samples (theta_k = 1) of each on its own row; DoS of either shaded."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    n = min(a_run.N, b_run.N)
    ta, tb = np.asarray(a_run.arrays["t"], float), np.asarray(b_run.arrays["t"], float)
    sa, sb = _run_spans(a_run), _run_spans(b_run)
    with figstyle.style(size):
        fig, axs = figstyle.subplots(size, 3, 1, aspect=0.25 if size == "page" else 0.42, sharex=True,
                                     height_ratios=[2.2, 1.4, 0.8])
        axs = axs[:, 0]
        xa, xb = np.asarray(a_run.arrays["x"], float), np.asarray(b_run.arrays["x"], float)
        handles: list[Artist] = []
        for i in range(xa.shape[1]):
            c = figstyle.CYCLE[i % len(figstyle.CYCLE)]
            axs[0].plot(ta, xa[:, i], color=c, ls=figstyle.AB_STYLES[0])
            if i < xb.shape[1]:
                axs[0].plot(tb, xb[:, i], color=c, ls=figstyle.AB_STYLES[1])
            handles.append(Line2D([], [], color=c, label=f"$x_{{{i + 1}}}$"))
        handles += [Line2D([], [], color="0.3", ls=figstyle.AB_STYLES[0], label=f"{names[0]} (solid)"),
                    Line2D([], [], color="0.3", ls=figstyle.AB_STYLES[1], label=f"{names[1]} (dashed)")]
        axs[0].set_ylabel("state $x$")
        if n and xa.shape[1:] == xb.shape[1:]:
            err = np.abs(xa[:n] - xb[:n]).max(axis=1)
            axs[1].semilogy(ta[:n], np.where(err > 0, err, np.nan), ".", color=figstyle.BLACK, ms=2)
            if not np.any(err > 0):
                axs[1].text(0.5, 0.5, "$x_A = x_B$ at every sample", transform=axs[1].transAxes, ha="center",
                            va="center")
        axs[1].set_ylabel("$\\|x_A - x_B\\|_\\infty$")
        for row, (run, t, _name) in enumerate(((a_run, ta, names[0]), (b_run, tb, names[1]))):
            lost = np.asarray(run.arrays["theta"]).astype(bool)
            axs[2].plot(t[lost], np.full(int(lost.sum()), 1 - row), "|", color=figstyle.VERMILLION, ms=6, mew=1.0)
        axs[2].set_yticks([1, 0], [names[0], names[1]])
        axs[2].set_ylim(-0.6, 1.6)
        axs[2].set_ylabel("lost ($\\theta_k = 1$)")
        axs[2].grid(False, axis="y")
        axs[2].set_xlabel("time $t$ [s]")
        same = sa == sb
        for ax in axs:
            figstyle.shade_dos(ax, sa, T=a_run.scenario.T, label=False)
            if not same:
                for a, b in sb:
                    ax.axvspan(a, b, facecolor="none", edgecolor=figstyle.DOS_COLOR, hatch="///", lw=0)
        if sa:
            handles.append(figstyle.dos_handle("DoS" if same else f"DoS of {names[0]}"))
        if sb and not same:
            handles.append(Patch(facecolor="none", edgecolor=figstyle.DOS_COLOR, hatch="///",
                                 label=f"DoS of {names[1]}"))
        handles.append(Line2D([], [], ls="", marker="|", color=figstyle.VERMILLION, ms=6, label="lost sample"))
        tmax = max(ta[-1] if len(ta) else 0, tb[-1] if len(tb) else 0)
        axs[0].set_xlim(0, tmax + a_run.scenario.T)
        if title:
            axs[0].set_title(title)
        figstyle.legend_below(fig, handles, ncol=4 if size == "column" else 6)
        return figstyle.save(fig, path)
