"""The deterministic numbers of the docs, produced in one place.

    python docs/make_numbers.py            # compute them, write docs/numbers.md, fill every marker,
    python docs/make_numbers.py --check    # compute them and compare: exit 1 and a diff when a page is stale

Every number on these pages that does not depend on the machine (the analysis of the paper's
example, the bundled scenarios' outcomes, the worst attack, the region of attraction, the sweeps)
comes from the commands below, run here as a user would run them (``testbed ... --json``). A page
holds a number as ``<!--n:NAME-->value<!--/n-->`` and a table as ``<!--numbers:NAME-->`` ...
``<!--/numbers-->``; this script rewrites what is between the markers and nothing else (the
figures and their data come from ``docs/make_figures.py``). A slow-tier test runs ``--check``
(``tests/repo/test_docs.py``). Timing figures are not here: they depend on the
machine, and ``docs/benchmarks.md`` names the benchmark that measures each.
"""

from __future__ import annotations

import argparse
import difflib
import json
import math
import os
import re
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent
PAGES = [ROOT / "README.md", *sorted(DOCS.glob("*.md"))]


INLINE = re.compile(r"<!--n:([a-z0-9_]+)-->(.*?)<!--/n-->", re.S)
BLOCK = re.compile(r"(<!--numbers:([a-z0-9_]+)-->\n)(.*?)(<!--/numbers-->)", re.S)


def testbed(*args: str) -> dict:
    """``testbed ARGS --json`` as a user runs it (exit 0 or 1: a run that escaped or failed is a result)."""
    r = subprocess.run([sys.executable, "-m", "testbed.cli", *args, "--json"], capture_output=True, text=True,
                       cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)), timeout=1800)
    if r.returncode not in (0, 1) or not r.stdout.strip():
        raise SystemExit(f"testbed {' '.join(args)}: exit {r.returncode}\n{r.stderr[-2000:]}")
    return json.loads(r.stdout)


def g(v, digits: int = 4) -> str:
    """A number as the docs print it: ``digits`` significant digits, no trailing noise."""
    if v is None:
        return "n/a"
    if isinstance(v, int):
        return f"{v:,}".replace(",", " ") if abs(v) >= 10000 else str(v)
    if v == 0:
        return "0"
    a = abs(v)
    if a >= 1e5 or a < 1e-3:
        m, e = f"{v:.{max(digits - 1, 0)}e}".split("e")
        return f"{m.rstrip('0').rstrip('.')}e{int(e)}"
    out = f"{v:.{digits}g}"
    if "e" in out:  # 4e+04 -> 4e4
        m, e = out.split("e")
        out = f"{m}e{int(e)}"
    return out


def pct(v: float, digits: int = 3) -> str:
    return f"{100 * v:.{digits}g} %"


def _scenario_variant(name: str, tmp: Path, fname: str, **changes) -> str:
    """A bundled scenario with some keys changed, as a file (``changes``: {section: {key: value}})."""
    from testbed import scenario

    d = tomllib.loads(scenario.load(name).source)
    for section, kv in changes.items():
        d.setdefault(section, {}).update(kv)
    f = tmp / fname
    f.write_text(_toml(d))
    return str(f)


def _toml(d: dict) -> str:
    def val(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, (int, float)):
            return repr(v)
        if isinstance(v, list):
            return "[" + ", ".join(val(x) for x in v) + "]"
        if isinstance(v, dict):
            return "{ " + ", ".join(f"{k} = {val(x)}" for k, x in v.items()) + " }"
        raise TypeError(v)

    top = [f"{k} = {val(v)}" for k, v in d.items() if not isinstance(v, dict)]
    secs = [f"[{k}]\n" + "\n".join(f"{kk} = {val(vv)}" for kk, vv in v.items()) for k, v in d.items()
            if isinstance(v, dict)]
    return "\n".join(top) + "\n\n" + "\n\n".join(secs) + "\n"


def compute() -> tuple[dict[str, str], dict[str, str]]:
    """(inline values, tables) of every page."""
    from testbed import scenario

    n: dict[str, str] = {}
    b: dict[str, str] = {}

    # ---- the bundled scenarios
    rows = ["| scenario | samples | lost | saturations | final \\|\\|x\\|\\|_inf | outcome |", "|---|---|---|---|---|---|"]
    sims = {}
    for name in scenario.bundled_names():
        s = testbed("simulate", name)
        sims[name] = s
        outcome = "converged" if s["converged"] else ("escaped" if s["escaped"] else "not converged")
        rows.append(f"| `{name}` | {len(s['t'])} | {s['packets_dropped']} | {s['saturations']} | "
                    f"{g(s['final_norm'], 3)} | {outcome} |")
    b["bundled_scenarios"] = "\n".join(rows)
    n["paper_final_norm"] = g(sims["paper"]["final_norm"], 2)
    n["paper_escape_final"] = g(sims["paper-escape"]["final_norm"], 3)

    # ---- model mismatch: the paper's quantizer against the resilient one
    mm = sims["paper-mismatch"]
    mi = testbed("simulate", "paper-mismatch", "--mode", "ideal")
    b["mismatch"] = "\n".join([
        "| command | saturations | first at sample | final \\|\\|x\\|\\|_inf | outcome |", "|---|---|---|---|---|",
        *(f"| `testbed simulate paper-mismatch{flag}` | {s['saturations']} | "
          f"{s['saturated_at'][0] if s['saturated_at'] else '-'} | {g(s['final_norm'], 2)} | "
          f"{'converged' if s['converged'] else ('escaped' if s['escaped'] else 'not converged')} |"
          for flag, s in (("", mm), (" --mode ideal", mi)))])
    n["mismatch_saturations"] = str(mm["saturations"])
    n["mismatch_ideal_saturations"] = str(mi["saturations"])

    # ---- physical timing on the paper's example
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        ph = testbed("simulate", "paper", "--timing", "physical")
        n["physical_scheduled_final"] = g(ph["final_norm"], 2)
        rows = ["| timing | actuation | rule | latency of u_k | declared bound | saturations | outcome |",
                "|---|---|---|---|---|---|---|"]
        rows.append(f"| physical | scheduled at 20 ms | delay-aware | 0 | 20 ms (a point) | {ph['saturations']} | "
                    f"{'converged' if ph['converged'] else 'escaped'} |")
        for w in (0.0005, 0.001, 0.002):
            lo, hi = 0.003 - w, 0.003 + w
            f = _scenario_variant("paper", tmp, f"w{w}.toml", run={
                "timing": "physical", "actuation": "arrival",
                "delay": {"nominal": 0.003, "min": lo, "max": hi},
                "delay_lost": {"nominal": 0.0422, "min": 0.0407, "max": 0.0437},
                "sim_delay": {"kind": "uniform", "min": lo, "max": hi, "seed": 1}})
            s = testbed("simulate", f)
            rows.append(f"| physical | on arrival | delay-aware | uniform in [{g(lo * 1e3)}, {g(hi * 1e3)}] ms | the "
                        f"same | {s['saturations']} | {'converged' if s['converged'] else 'escaped'} |")
        f = _scenario_variant("paper", tmp, "paperrule.toml", run={
            "timing": "physical", "actuation": "arrival",
            "sim_delay": {"kind": "uniform", "min": 0.002, "max": 0.008, "seed": 1}}, quantizer={"rule": "paper"})
        s = testbed("simulate", f)
        rows.append(f"| physical | on arrival | paper | uniform in [2, 8] ms | - | {s['saturations']} | "
                    f"{'converged' if s['converged'] else 'escaped'} |")
        b["physical_timing"] = "\n".join(rows)

        # ---- escape along the ray through the paper's x0
        conv, esc = [], []
        for i in range(4, 17):
            sx = i / 4
            f = _scenario_variant("paper", tmp, f"ray{i}.toml", plant={"x0": [0.1 * sx, 0.1 * sx]},
                                  quantizer={"E0": max(0.1, 0.1 * sx)})
            (esc if testbed("simulate", f)["escaped"] else conv).append(sx)
        n["ray_escapes"] = ", ".join(g(v) for v in esc)
        n["ray_converges"] = ", ".join(g(v) for v in conv)

    # ---- Theorems 1 and 2, the region of attraction, the sweeps, vulnerable states
    a = testbed("analyze", "paper", "--full", "--escape-x0", "0.3", "0.3", "--no-progress")
    t1, t2 = a["theorem1"], a["theorem2"]
    n["rho_phi0"] = g(a["rho_Phi0"])
    n["rho_phi1"] = g(a["rho_Phi1"])
    n["lambda2"] = g(a["Lambda"] ** 2)
    n["rho_d_limit"] = g(math.log(1 / a["rho_Phi0"] ** 2) / math.log(a["Lambda"] ** 2 / a["rho_Phi0"] ** 2), 4)
    pl, pa, ti = t1["plain"], t1["paper"], t1["tight"]
    c = t1["certificate"]
    b["theorem1"] = "\n".join([
        "| choice | phi_0 | phi_1 | mu_0 = mu_1 | nu_0 | nu_1 | rho_D_max | rho_F_max [1/s] |",
        "|---|---|---|---|---|---|---|---|",
        f"| plain (dlyap with I) | {g(pl['phi0'])} | {g(pl['phi1'])} | {g(pl['mu0'])} | {g(pl['nu0'])} | "
        f"{g(pl['nu1'])} | {g(pl['rho_D_max'], 3)} | {g(pl['rho_F_max'], 3)} |",
        f"| optimized, (mu0)/(mu1) (default) | {g(c['phi0'], 6)} | {g(c['phi1'])} | {g(c['mu0'])} | {g(c['nu0'])} | "
        f"{g(c['nu1'])} | **{g(pa['rho_D_max'], 3)}** | **{g(pa['rho_F_max'], 4)}** |",
        f"| optimized, smallest mu of (mu) | {g(c['phi0'], 6)} | {g(c['phi1'])} | 1 (common P) | {g(c['nu0'])} | "
        f"{g(c['nu1'])} | {g(ti['rho_D_max'], 3)} | {g(ti['rho_F_max'], 4)} |"])
    n["area_plain"] = g(pl["rho_D_max"] * pl["rho_F_max"] / 2, 2)
    n["area_paper"] = g(pa["area"], 2)
    n["area_tight"] = g(ti["area"], 3)
    n["rho_d_max"] = g(pa["rho_D_max"], 3)
    n["rho_f_max"] = g(pa["rho_F_max"], 3)
    n["rho_f_max_tight"] = g(ti["rho_F_max"], 3)
    n["c0"] = g(t2["c0"])
    n["c1"] = g(t2["c1"])
    n["d_prime"] = g(t2["d_prime"])
    n["d"] = g(t2["d"], 3)
    n["delta_scale"] = g(t2["d_prime"] / t2["d"], 3)
    b["theorem2"] = "\n".join([
        "| gamma | delta | epsilon | eta_0 | alpha | beta | omega_0 | omega_1 | E_0 bound |",
        "|---|---|---|---|---|---|---|---|---|",
        f"| {g(a['gamma'], 3)} (auto) | {g(a['delta'], 3)} | {g(t2['eps'])} | {g(t2['eta0'], 3)} | {g(t2['alpha'])} | "
        f"{g(t2['beta'], 3)} | {g(t2['omega0'])} | {g(t2['omega1'], 5)} | {g(a['E0_bound'], 2)} |"])
    n["gamma_auto"] = g(a["gamma"], 3)
    n["delta"] = g(a["delta"], 3)
    n["e0_bound"] = g(a["E0_bound"], 2)
    n["gamma_paper_delta"] = g(a["gamma_for_paper_delta"], 3)
    dt = {row["gamma"]: row["delta"] for row in a["delta_table"]}
    n["delta_at_1e13"] = g(dt[1e-13], 2)
    n["delta_at_1e6"] = g(dt[1e-6], 2)
    n["delta_at_1e3"] = g(dt[1e-3], 2)
    n["delta_ratio"] = g(a["delta"] / 1.94e-7, 1)
    n["sqrt_alpha_beta"] = g(math.sqrt(t2["alpha"] / t2["beta"]), 2)
    n["vartheta"] = g(t2["vartheta"], 1)
    r = a["roa"]
    n["roa_fraction"] = pct(r["fraction_inside"], 2)
    n["roa_area"] = g(r["area"], 3)
    v, v0 = a["vulnerable"], a["vulnerable_baseline"]
    vb = v["budget"]
    n["vulnerable_budget"] = (f"kappa_F = {g(vb['kappa_F'])}, rho_F = {g(vb['rho_F'])}, kappa_D = {g(vb['kappa_D'])}, "
                              f"rho_D = {g(vb['rho_D'])}")
    n["vulnerable_fraction"] = pct(v["fraction_vulnerable"], 2)
    n["vulnerable_baseline"] = pct(v0["fraction_vulnerable"], 2)
    sw = a["sweep"]
    rD, eb = sw["rho_D"], sw["empirical_boundary"]
    full = [d for d, e in zip(rD, eb) if e is not None and e >= max(sw["rho_F"]) - 1e-12]
    n["sweep_full_rho_d"] = g(max(full)) if full else "0"
    n["sweep_rho_f_max"] = g(max(sw["rho_F"]))
    n["sweep_rho_d_at_f0"] = g(sw["empirical_rho_D_max_at_rho_F_0"])
    def mean(rows):  # as np.nanmean: budget points without a run of this kind are left out
        vals = [v for row in rows for v in row if v is not None]
        return sum(vals) / len(vals)

    frac = {k: mean(sw["converged"][k]) for k in sw["kinds"]}
    n["sweep_greedy"] = pct(frac["greedy"], 3)
    n["sweep_random"] = pct(frac["random"], 3)
    n["sweep_periodic"] = pct(frac["periodic"], 3)
    zoom_fail = sum(1 for row in a["sweep_zoom"]["worst_converged"] for ok in row if ok is not None and not ok)
    n["sweep_zoom_failures"] = str(zoom_fail)

    # ---- the strongest attacker
    w1 = testbed("worst-attack", "paper", "--no-progress")
    w3 = testbed("worst-attack", "paper", "--attacks", "3", "--no-progress", "--no-greedy")

    def ivs(x):
        return ", ".join(f"[{g(s)}, {g(L)}]" for s, L in x["intervals"])

    gr = w1["greedy"]
    rows = ["| attacker | intervals [start, length] (s) | lost samples | total duration | escapes | |",
            "|---|---|---|---|---|---|",
            "| the paper's two attacks | [1.0, 1.2], [4.0, 0.8] | "
            f"{sims['paper']['packets_dropped']} | 2.0 s | {'yes' if sims['paper']['escaped'] else 'no'} | "
            "converges (Fig. 2) |",
            f"| greedy online attacker (one attack), least kappa_D | {ivs(gr) if gr.get('intervals') else '-'} | "
            f"- | {g(gr.get('total_duration'))} s (kappa_D = {g(gr.get('kappa_D'))} s) | "
            f"{'yes' if gr.get('escaped') else 'no'} | |"]
    for f, p in zip(w3["front"], w3["proof"]):
        note = ("shorter by one sample at either end: converges" if f["attacks"] == 1 else
                f"proven: nothing below {p['samples_lost_below']} lost samples")
        rows.append(f"| at most {f['attacks']} attack{'s' if f['attacks'] > 1 else ''} "
                    f"({'exact' if f['exact'] else 'not proven minimal'}) | {ivs(f)} | {f['samples_lost']} | "
                    f"**{g(f['total_duration'])} s** | {'yes' if f['escaped'] else 'no'} | {note} |")
    b["worst_attack"] = "\n".join(rows)
    n["worst_single"] = f"{g(w1['total_duration'])} s"
    n["worst_single_packets"] = str(w1["samples_lost"])
    n["worst_three"] = f"{g(w3['total_duration'])} s"
    n["worst_proof_two"] = str(w3["proof"][1]["samples_lost_below"])
    n["escape_horizon"] = f"{g(w3['escape_criterion']['horizon_s'])} s"
    vu = testbed("vulnerability", "paper", "--grid", "41", "--no-progress")
    n["vuln_states"] = str(vu["states_in_region"])
    n["vuln_unattacked"] = str(vu["escape_unattacked"])
    n["vuln_one_packet"] = str(sum(1 for row in vu["samples"] for L in row if L == 1))
    n["vuln_median"] = f"{g(vu['median_duration'])} s"
    n["vuln_max"] = f"{g(vu['largest_duration'])} s"
    b.update(methods_numbers())
    nn, nb = noise_numbers()
    n.update(nn)
    b.update(nb)
    cn, cb = campaign_numbers()
    n.update(cn)
    b.update(cb)
    return n, b


NOISE_SCENARIO = "docs/examples/paper-noisy.toml"


def noise_numbers() -> tuple[dict[str, str], dict[str, str]]:
    """docs/plants-and-quantizer.md: E_min against sensor noise (``testbed noise``), and the bundled
    methods under the same noisy sensor (``testbed noise --method``)."""
    d = testbed("noise", NOISE_SCENARIO, "--no-progress")
    n = {"noise_growth": g(d["growth"]), "noise_settle": f"{g(d['settle_s'], 3)} s"}
    first = d["scales"][0]
    n["noise_guarantee_ratio"] = g(first["E_min_guarantee"] / first["b"], 2)
    n["noise_estimate_ratio"] = g(first["E_min_estimate"] / first["b"], 3)

    def escapes(entry):
        esc = [g(r["ratio"], 3) for r in entry["runs"] if r["escaped"]]
        return "none" if not esc else esc[0] if len(esc) == 1 else ", ".join(esc[:-1]) + " and " + esc[-1]

    by_scale = {e["scale"]: e for e in d["scales"]}
    n["noise_escapes_mid"] = escapes(by_scale[1e-5])
    n["noise_escapes_big"] = escapes(by_scale[1e-4])

    def cell(r):
        return "escaped" if r["escaped"] else f"{r['saturations_after']}, {g(r['tail_norm'], 2)}"

    rows = ["| E_min / b | " + " | ".join(f"noise {g(e['scale'])}: saturations, max \\|\\|x\\|\\|" for e in d["scales"])
            + " |", "|---" * (1 + len(d["scales"])) + "|"]
    for i, r0 in enumerate(d["scales"][0]["runs"]):
        rows.append(f"| {g(r0['ratio'], 3)} | " + " | ".join(cell(e["runs"][i]) for e in d["scales"]) + " |")
    tables = {"noise_sweep": "\n".join(rows)}
    rows = ["| method | E_min = 0: saturations (after settling) | max \\|\\|x\\|\\| after settling | "
            "E_min = 3 b: saturations | max \\|\\|x\\|\\| after settling |", "|---|---|---|---|---|"]
    for m in METHODS:
        e = testbed("noise", NOISE_SCENARIO, "--method", m, "--scale", "1e-5", "--ratio", "0", "3",
                    "--no-progress")["scales"][0]
        a, c = e["runs"]
        rows.append(f"| `{m}` | {a['saturations']} ({a['saturations_after']}) | "
                    f"{'escaped' if a['escaped'] else g(a['tail_norm'], 2)} | {c['saturations']} ({c['saturations_after']}) | "
                    f"{'escaped' if c['escaped'] else g(c['tail_norm'], 2)} |")
    tables["noise_methods"] = "\n".join(rows)
    return n, tables


METHODS = ["paper", "zoom", "static", "unquantized", "unquantized-hold"]


def methods_numbers() -> dict[str, str]:
    """docs/methods.md: every bundled method on the paper's example and attack (``testbed versus``), and
    the least single attack that defeats each from x0 (``testbed worst-attack --method``)."""
    v = testbed("versus", "paper", "--methods", ",".join(METHODS))
    rows = ["| method | bits/sample | lost | saturations | max \\|\\|x\\|\\|_inf | final \\|\\|x\\|\\|_inf | settles at sample "
            "| outcome | least single attack that escapes |", "|---|---|---|---|---|---|---|---|---|"]
    for r in v["rows"]:
        w = testbed("worst-attack", "paper", "--method", r["method"], "--no-progress")
        iv = w.get("intervals") or []
        least = (f"{w['samples_lost']} samples ({g(w['total_duration'])} s)" if iv and w.get("escaped")
                 else ("none needed: escapes unattacked" if w.get("escaped") else "none found"))
        outcome = "converged" if r["converged"] else ("escaped" if r["escaped"] else "not converged")
        rows.append(f"| `{r['method']}` | {r['bits']} | {r['samples_lost']} | {r['saturations']} | {g(r['max_norm'], 3)} | "
                    f"{g(r['final_norm'], 3)} | {r['settle_samples'] if r['settle_samples'] is not None else '-'} | "
                    f"{outcome} | {least} |")
    return {"methods_versus": "\n".join(rows)}


CAMPAIGN = "docs/examples/campaign-methods.toml"


def campaign_numbers() -> tuple[dict[str, str], dict[str, str]]:
    """docs/campaigns.md: the worked example (``testbed campaign ... --json``, then ``--table markdown`` of the
    same folder, which runs nothing more)."""
    with tempfile.TemporaryDirectory() as d:
        s = testbed("campaign", CAMPAIGN, "--out", d, "--no-progress")["summary"]
        r = subprocess.run([sys.executable, "-m", "testbed.cli", "campaign", CAMPAIGN, "--out", d, "--no-progress",
                            "--table", "markdown"], capture_output=True, text=True, cwd=ROOT,
                           env=dict(os.environ, PYTHONPATH=str(ROOT)), timeout=1800)
        if r.returncode != 0:
            raise SystemExit(f"testbed campaign {CAMPAIGN} --table markdown: exit {r.returncode}\n{r.stderr[-2000:]}")
    by = {g["value"]: g for g in s["by_axis"]["method.name"]}
    n = {f"campaign_{m}": f"{g['converged']}/{g['bounded']}/{g['escaped']} of {g['n']}" for m, g in by.items()}
    zoom = next(d for d in s["comparisons"]["method.name"]["values"] if d["value"] == "zoom")["paired_difference"]
    n["campaign_zoom_diff"] = f"{zoom['difference']:+.2f} [{zoom['ci95'][0]:.2f}, {zoom['ci95'][1]:.2f}]"
    n["campaign_zoom_p"] = "p < 0.001" if zoom["mcnemar_p"] < 0.001 else f"p = {zoom['mcnemar_p']:.3g}"
    return n, {"campaign_methods": r.stdout.strip()}


def render(n: dict[str, str], b: dict[str, str]) -> dict[Path, str]:
    """Every page with its markers filled (docs/numbers.md is written whole)."""
    out = {}
    used_n, used_b = set(), set()
    for page in PAGES:
        if page.name == "numbers.md":
            continue
        text = page.read_text()

        def inline(m, page=page):
            if m.group(1) not in n:
                raise SystemExit(f"{page.name}: unknown number {m.group(1)!r}")
            used_n.add(m.group(1))
            return f"<!--n:{m.group(1)}-->{n[m.group(1)]}<!--/n-->"

        def block(m, page=page):
            if m.group(2) not in b:
                raise SystemExit(f"{page.name}: unknown table {m.group(2)!r}")
            used_b.add(m.group(2))
            return f"{m.group(1)}{b[m.group(2)]}\n{m.group(4)}"

        out[page] = BLOCK.sub(block, INLINE.sub(inline, text))
    lines = ["# The generated numbers", "",
             "Written by `python docs/make_numbers.py` from `testbed ... --json` runs (the commands are in the script); "
             "`tests/repo/test_docs.py` checks, in the slow tier, that every page is current. Nothing on this page "
             "depends on the machine.", ""]
    titles = {"bundled_scenarios": "Bundled scenarios (`testbed simulate NAME`)",
              "mismatch": "Model mismatch (`testbed simulate paper-mismatch`)",
              "physical_timing": "Physical timing on the paper's example (`testbed simulate ... --timing physical`)",
              "theorem1": "Theorem 1 (`testbed analyze paper`)", "theorem2": "Theorem 2 (`testbed analyze paper`)",
              "worst_attack": "The strongest attacker (`testbed worst-attack paper`)",
              "methods_versus": "Methods on the paper's example (`testbed versus paper --methods ...`, "
                                "`testbed worst-attack paper --method ...`)",
              "noise_sweep": "E_min against sensor noise (`testbed noise docs/examples/paper-noisy.toml`)",
              "noise_methods": "The bundled methods under sensor noise (`testbed noise ... --method NAME`)",
              "campaign_methods": "The worked campaign (`testbed campaign docs/examples/campaign-methods.toml "
                                  "--table markdown`)"}
    for key, table in b.items():
        lines += [f"## {titles.get(key, key)}", "", f"<!--numbers:{key}-->", table, "<!--/numbers-->", ""]
    lines += ["## Values", "", "| name | value |", "|---|---|"]
    lines += [f"| `{k}` | <!--n:{k}-->{v}<!--/n--> |" for k, v in sorted(n.items())]
    out[DOCS / "numbers.md"] = "\n".join(lines) + "\n"
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="compare with the pages instead of writing them")
    args = ap.parse_args()
    sys.path.insert(0, str(ROOT))
    n, b = compute()
    pages = render(n, b)
    stale = []
    for page, text in pages.items():
        old = page.read_text() if page.exists() else ""
        if old != text:
            stale.append(page)
            if args.check:
                sys.stdout.writelines(difflib.unified_diff(old.splitlines(True), text.splitlines(True),
                                                           str(page.relative_to(ROOT)), "generated"))
            else:
                page.write_text(text)
    if args.check:
        print(f"{len(stale)} page(s) stale: {', '.join(p.name for p in stale)}" if stale else "every page is current")
        return 1 if stale else 0
    print(f"wrote {len(stale)} page(s)" + (f": {', '.join(p.name for p in stale)}" if stale else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
