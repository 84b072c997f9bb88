"""A campaign's paired comparisons and the table a paper includes (``testbed campaign ... --table
latex|markdown``; ``summary.md``).

A campaign's design is paired: the runs of two values of an axis (two methods, say) that share every
other axis value, the repeat and the seeds faced the same attack from the same initial state.  For every
axis of more than one value that is not a seed, each value is compared with the axis's first value (the
reference) over those pairs (``engine.compare_paired``: the statistics of ``testbed.common.comparestats``).
"""

from __future__ import annotations

import json
from collections.abc import Sequence

from . import engine
from .spec import SEED_KEYS

#: the axes that are the pairing itself, never compared
SEED_AXES = tuple(SEED_KEYS.values())
#: the bootstrap's seed in a campaign's comparisons
BOOTSTRAP_SEED = 0


def compared_axes(axes: dict) -> list[str]:
    """The axes compared value by value: more than one value, not a seed."""
    return [k for k, v in axes.items() if len(v) > 1 and k not in SEED_AXES]


def _key(row: dict, axis: str, axes: dict) -> str:
    """What pairs a row with the rows of the other values of ``axis``: the other axes, the repeat, the seeds."""
    other = {k: row.get(k) for k in axes if k != axis}
    seeds = {k: row.get(k) for k in SEED_KEYS}
    return json.dumps([other, row.get("repeat"), seeds], sort_keys=True, default=str)


def comparisons(axes: dict, rows: list[dict]) -> dict:
    """Per compared axis: ``{"reference": first value, "values": [{"value", "vs", "pairs", "unpaired",
    "paired_difference", "paired_escaped", "paired_continuous"}, ...]}`` (each value but the first, minus
    the first, over the rows of status ok paired as the module says)."""
    ok = [r for r in rows if r.get("status") == "ok"]
    out = {}
    for axis in compared_axes(axes):
        ref = axes[axis][0]
        refs: dict[str, dict] = {}
        for r in ok:
            if _same(r.get(axis), ref):
                refs.setdefault(_key(r, axis, axes), r)
        values = []
        for v in axes[axis][1:]:
            mine = [r for r in ok if _same(r.get(axis), v)]
            pairs = [(r, refs[_key(r, axis, axes)]) for r in mine if _key(r, axis, axes) in refs]
            values.append({"value": v, "vs": ref, "pairs": len(pairs), "unpaired": len(mine) - len(pairs),
                           **engine.compare_paired(pairs, seed=BOOTSTRAP_SEED)})
        out[axis] = {"reference": ref, "values": values}
    return out


def _same(a: object, b: object) -> bool:
    if isinstance(a, str) and not isinstance(b, str):  # an axis of mixed values is JSON text in the table
        return a == json.dumps(b)
    return a == b or (isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)) and list(a) == list(b))


# ============================================================================ formatting
def fmt_p(p: float | None) -> str:
    """A p value as a table prints it: ``p = 0.0625``, ``p < 0.001`` (``p -`` without one)."""
    if p is None:
        return "p -"
    return "p < 0.001" if p < 0.001 else f"p = {p:.3g}"


def fmt_ci(est: float | None, ci: Sequence[float] | None, spec: str = "+.2f") -> str:
    """``est [lo, hi]`` (the estimate signed; ``-`` without an estimate, the estimate alone without an
    interval)."""
    if est is None:
        return "-"
    s = format(est, spec)
    plain = spec.lstrip("+")
    return s if ci is None else f"{s} [{format(ci[0], plain)}, {format(ci[1], plain)}]"


def _rate(g: dict) -> str:
    w = g.get("wilson95")
    if not g.get("n"):
        return "-"
    return f"{g['successes']}/{g['n']} = {g['success_rate']:.2f}" + ("" if w is None else f" [{w[0]:.2f}, {w[1]:.2f}]")


def _paired_cell(d: dict, key: str, spec: str) -> str:
    if key in ("paired_difference", "paired_escaped"):
        x = d[key]
        return f"{fmt_ci(x['difference'], x['ci95'])}, {fmt_p(x['mcnemar_p'])}"
    c = d["paired_continuous"][key]
    extra = f" ({c['n']} pairs)" if c["missing"] else ""
    return f"{fmt_ci(c['median_difference'], c['ci95'], spec)}, {fmt_p(c['wilcoxon_p'])}{extra}"


#: the paired columns of the table: (key, heading, number format)
PAIRED_COLUMNS = (("paired_difference", "Δ converged", "+.2f"), ("paired_escaped", "Δ escaped", "+.2f"),
                  ("settle_samples", "Δ settle samples", "+.3g"), ("max_norm", "Δ max norm", "+.3g"),
                  ("saturations", "Δ saturations", "+.3g"))


def table_rows(summary: dict) -> list[tuple[str, str, list[list[str]], str]]:
    """(axis, reference, cells of each row, note) per compared axis (or the totals alone when none is)."""
    out = []
    comps = summary.get("comparisons") or {}
    for axis, comp in comps.items():
        groups = {json.dumps(g["value"], sort_keys=True): g for g in summary["by_axis"][axis]}
        cells = []
        ref_label = _label(comp["reference"])
        g0 = groups[json.dumps(comp["reference"], sort_keys=True)]
        cells.append([f"{ref_label} (reference)", str(g0["runs"]), _rate(g0), str(g0["bounded"]), str(g0["escaped"]),
                      *(["-"] * len(PAIRED_COLUMNS))])
        pairs = set()
        for d in comp["values"]:
            g = groups[json.dumps(d["value"], sort_keys=True)]
            pairs.add(d["pairs"])
            cells.append([_label(d["value"]), str(g["runs"]), _rate(g), str(g["bounded"]), str(g["escaped"]),
                          *(_paired_cell(d, k, spec) for k, _, spec in PAIRED_COLUMNS)])
        npairs = ", ".join(str(p) for p in sorted(pairs))
        note = (f"Δ: value minus {ref_label} on the same seeds and initial states ({npairs} pairs); "
                "converged: 95 % Wilson interval; Δ converged, Δ escaped: Newcombe hybrid score interval, exact "
                "McNemar p; Δ settle samples, max norm (of ||x_k||_inf), saturations: median of the paired "
                "differences, percentile bootstrap interval, Wilcoxon signed-rank p. bounded: neither converged nor "
                "escaped by the end of the run.")
        out.append((axis, ref_label, cells, note))
    if not out:
        t = summary["total"]
        out.append(("all", "", [["all", str(t["runs"]), _rate(t), str(t["bounded"]), str(t["escaped"])]],
                    "converged: 95 % Wilson interval; no axis of more than one value to compare."))
    return out


HEAD = ("runs", "converged [95 % CI]", "bounded", "escaped")


def _label(v: object) -> str:
    return v if isinstance(v, str) else json.dumps(v)


def markdown(summary: dict) -> str:
    """The comparison tables in Markdown (one per compared axis)."""
    lines = []
    for axis, _ref, cells, note in table_rows(summary):
        head = [axis, *HEAD, *(h + " [95 % CI], p" for _, h, _ in PAIRED_COLUMNS)][:len(cells[0])]
        lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        lines += ["| " + " | ".join(c.replace("|", "\\|") for c in row) + " |" for row in cells]
        lines += ["", note.replace("||x_k||_inf", "\\|\\|x_k\\|\\|_inf"), ""]
    return "\n".join(lines).rstrip() + "\n"


_TEX = {"\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#", "_": r"\_", "{": r"\{",
        "}": r"\}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}"}


def _tex(s: str) -> str:
    s = "".join(_TEX.get(ch, ch) for ch in s)
    return s.replace("Δ", r"$\Delta$").replace("||x\\_k||\\_inf", r"$\|x_k\|_\infty$").replace("p < 0.001", r"$p < 0.001$")


def _tex_num(cell: str) -> str:
    """Signs of numbers as math minus signs."""
    import re

    return re.sub(r"(?<![\w.])-(?=\d)", "$-$", re.sub(r"(?<![\w.])\+(?=\d)", "$+$", cell))


def latex(summary: dict, label: str = "campaign") -> str:
    """The comparison tables as LaTeX ``table*`` floats (booktabs rules)."""
    out = ["% testbed campaign --table latex (needs \\usepackage{booktabs})"]
    for axis, _ref, cells, note in table_rows(summary):
        head = [axis, *HEAD, *(h for _, h, _ in PAIRED_COLUMNS)][:len(cells[0])]
        out += [r"\begin{table*}", r"\centering", r"\footnotesize",
                rf"\caption{{Campaign {_tex(summary.get('campaign', ''))}, by {_tex(axis)}. {_tex(note)}}}",
                rf"\label{{tab:{label}-{axis.replace('.', '-')}}}",
                r"\begin{tabular}{l" + "r" * 4 + "l" * (len(head) - 5) + "}", r"\toprule",
                " & ".join(_tex(h) for h in head) + r" \\", r"\midrule"]
        out += [" & ".join(_tex_num(_tex(c)) for c in row) + r" \\" for row in cells]
        out += [r"\bottomrule", r"\end{tabular}", r"\end{table*}"]
    return "\n".join(out) + "\n"
