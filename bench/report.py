"""The report: the targets' verdicts, a Markdown table, a JSON dump and a log-log plot of speed against error.

A run's results are one dict (`res`, built by bench/__main__.py); the keys this module reads:
command, machine, scene, n_big, core_modes, core {N: [seconds per mode or None]}, peers, variants,
ratios, speedup {"egh", "e"}, targets, notes, and optionally all_active, http, active, memory.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

RESULTS = Path(__file__).parent / "results"
EPS = 2.0**-52  # float64 machine epsilon: errors are also shown in its units
CORE = "core float64 exact"  # the variant the targets are about
JAX = "JAX jit(vmap), same inputs"  # the peer they are measured against
WARP = "Warp CPU kernel, same inputs"  # bench/peer_warp.py: energy and energy + gradient (wp.Tape), 1 thread
FLOOR = "memory-write floor"  # a speed bound that computes nothing: no error, not on the Pareto front
ALL_ACTIVE = ", all active"  # suffix of a variant timed on the scene with every joint outside its range


def core_threads(threads: int) -> str:
    """The name of the core variant timed on `threads` threads (the targets' speed; its answers are CORE's, bitwise)."""
    return f"{CORE}, {threads} threads"


def count(n: int) -> str:
    """A joint count as the issue writes it: 1e5 for a power of ten from 100 on, else the integer (300)."""
    n = int(n)
    k = len(str(n)) - 1
    return f"1e{k}" if n >= 100 and n == 10**k else str(n)


def _fmt(x: Any, spec: str = ".3g") -> str:
    """A number for a table cell; "-" for a missing one."""
    if x is None:
        return "-"
    if isinstance(x, str):
        return x
    return format(x, spec)


def pareto(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the non-dominated `(error, speed)` points (lower error, higher speed), sorted by error.

    A point is dropped when another has error <= and speed >= (the first of exact duplicates stays).
    """
    order = sorted(range(len(points)), key=lambda i: (points[i][0], -points[i][1]))
    front: list[int] = []
    best = float("-inf")
    for i in order:
        if points[i][1] > best:
            front.append(i)
            best = points[i][1]
    return front


# ------------------------------------------------------------------ targets


def _verdict(group: int, target: str, measured: str, required: str, shortfall: float | None) -> dict[str, Any]:
    """One row of the targets table (of target `group`, 1 to 4); `shortfall` >= 1 is the factor by which it is
    missed (None: met)."""
    met = shortfall is None
    return {"group": group, "target": target, "measured": measured, "required": required, "met": met,
            "status": "**met**" if met else f"**missed** by {shortfall:.2f}x"}


def _at_least(group: int, target: str, got: float, want: float, fmt: str) -> dict[str, Any]:
    return _verdict(group, target, fmt.format(got), ">= " + fmt.format(want), None if got >= want else want / got)


def _not_measured(group: int, target: str, required: str, why: str) -> dict[str, Any]:
    return {"group": group, "target": target, "measured": "-", "required": required, "met": None,
            "status": f"not measured: {why}"}


def _error_no_worse(family: str, core: float | None, jax: float | None) -> dict[str, Any]:
    """Core's Hessian error against JAX's (part of target 1): a plain `<=` on the two numbers, no tolerance."""
    target = f"1. Hessian error no worse than JAX's, {family} cases"
    if core is None or jax is None:
        return _not_measured(1, target, "core <= JAX", "no such cases")
    measured = f"core {core:.3g} ({core / EPS:.0f} eps) vs JAX {jax:.3g} ({jax / EPS:.0f} eps)"
    # A zero JAX error with a nonzero core error cannot be put as a ratio: say it is infinitely missed.
    short = None if core <= jax else (core / jax if jax > 0 else float("inf"))
    return _verdict(1, target, measured, "core <= JAX", short)


def targets(res: dict[str, Any], jax_missing: str = "JAX peer not run") -> list[dict[str, Any]]:
    """The issue's four targets, each met or missed by how much (the first has a speed and two error parts)."""
    n = count(res["n_big"])
    sp, v = res.get("speedup", {}), {x["name"]: x for x in res["variants"]}
    rows = []
    if sp.get("egh") is not None and JAX in v:
        best = res.get("best_threads", {})

        def cores(m: str) -> str:
            return f"core (the faster of 1 and {res.get('threads', 1)} threads: {best.get(m, 1)})"

        rows.append(_at_least(1, f"1. E+G+H exact at {n}: {cores('egh')} vs JAX on all cores, throughput (same inputs)",
                              sp["egh"], 3.0, "{:.2f}x"))
        core, jax = v[CORE], v[JAX]
        for family, key in (("well-conditioned", "err"), ("hard", "err_hard")):
            rows.append(_error_no_worse(family, (core.get(key) or {}).get("H"), (jax.get(key) or {}).get("H")))
        rows.append(_at_least(2, f"2. energy at {n}: {cores('e')} vs JAX on all cores, throughput (same inputs)", sp["e"],
                              3.0, "{:.2f}x"))
    else:
        rows.append(_not_measured(1, f"1. E+G+H exact at {n} vs JAX, Hessian error no worse", ">= 3x", jax_missing))
        rows.append(_not_measured(2, f"2. energy at {n} vs JAX", ">= 3x", jax_missing))
    m = res.get("memory")
    if m:
        got = m["peak"] / m["output"]
        rows.append(_verdict(3, f"3. peak memory / output size, E+G+H exact at {count(m['n'])}", f"{got:.2f}x",
                             "<= 2.5x", None if got <= 2.5 else got / 2.5))
    else:
        rows.append(_not_measured(3, "3. peak memory / output size", "<= 2.5x", "full run only"))
    h = res.get("http")
    if h and "binary_vs_inprocess_1e4_active_only" in h:
        rows.append(_at_least(4, "4. binary HTTP at 1e4 joints vs in-process throughput, active_only (a solver's request)",
                              h["binary_vs_inprocess_1e4_active_only"], 0.5, "{:.0%}"))
        rows.append(_at_least(4, "4'. the same with the full answer (every joint's dense Hessian, 90% of them zeros)",
                              h["binary_vs_inprocess_1e4_full"], 0.5, "{:.0%}"))
    else:
        why = "the binary encoding is not available" if h else "HTTP not run (full run without --no-http only)"
        rows.append(_not_measured(4, "4. binary HTTP at 1e4 joints vs in-process", ">= 50%", why))
    return rows


# ------------------------------------------------------------------ markdown


def _section(title: str, *body: str) -> list[str]:
    """A `##` section: a blank line, the title, a blank line, then the body lines."""
    return ["", f"## {title}", "", *body]


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)] + ["| " + " | ".join(r) + " |" for r in rows]


def _target_lines(res: dict[str, Any]) -> list[str]:
    rows = res["targets"]
    lines = ["\"missed by k\": the measured value must improve k-fold to meet the target. "
             "Errors are compared as measured, without tolerance.", ""]
    lines += _table(["target", "measured", "required", "status"],
                    [[t["target"], t["measured"], t["required"], t["status"]] for t in rows])
    first = [t for t in rows if t["group"] == 1]
    if len(first) > 1 and all(t["met"] is not None for t in first):
        ok = all(t["met"] for t in first)
        verdict = "**met**." if ok else "**missed** (see the rows above)."
        lines += ["", f"Target 1 (speed and Hessian error together): {verdict}"]
    return lines


def _variant_lines(res: dict[str, Any]) -> list[str]:
    def errs(d: dict | None) -> list[str]:
        return ["n/a"] * 3 if d is None else [_fmt(d.get(k)) for k in ("E", "G", "H")]

    rows = [[v["name"], _fmt(v.get("egh_jps")), _fmt(v.get("e_jps")), *errs(v.get("err")), *errs(v.get("err_hard"))]
            for v in res["variants"]]
    return ["Error: per case, max|got - ref| / max|ref| against the 50-digit reference (bench/reference.py), "
            "then the max over the cases of a family; psd variants against the psd reference. "
            "The memory-write floor computes nothing (error n/a).", "",
            *_table(["variant", "E+G+H joints/s", "energy joints/s", "E err (well)", "G err (well)", "H err (well)",
                     "E err (hard)", "G err (hard)", "H err (hard)"], rows)]


def _core_lines(res: dict[str, Any]) -> list[str]:
    rows = [[count(n)] + [f"{t:.3g} s ({int(n) / t:.3g}/s)" if t else "-" for t in ts]
            for n, ts in res["core"].items()]
    return _table(["N", *res["core_modes"]], rows)


def all_active_targets(a: dict[str, Any]) -> list[dict[str, Any]]:
    """Issue 11's targets on the all-active scene `a` (res["all_active"]): speed against JAX, share of the
    memory-write floor, psd against exact."""
    n, rows = count(a["n"]), []
    sp = a["speedup"]
    for m, want, what in (("egh", 5.0, "E+G+H exact"), ("e", 3.0, "energy")):
        target = f"{what} at {n}, every joint active, vs JAX (same inputs)"
        if sp.get(m) is None:
            rows.append(_not_measured(5, target, f">= {want:g}x", "JAX peer not run"))
        else:
            rows.append(_at_least(5, target, sp[m], want, "{:.2f}x"))
    rows.append(_at_least(5, f"E+G+H exact at {n}, every joint active: share of the memory-write floor",
                          a["floor_fraction_egh"], 0.15, "{:.0%}"))
    r = a.get("psd_over_exact")
    target = f"E+G+H psd / exact time at {n}, every joint active"
    rows.append(_not_measured(5, target, "<= 2x", "full run only") if r is None else
                _verdict(5, target, f"{r:.2f}x", "<= 2x", None if r <= 2.0 else r / 2.0))
    return rows


def warp_targets(a: dict[str, Any]) -> list[dict[str, Any]]:
    """Issue 22's targets on the all-active scene `a` (res["all_active"]): the core's energy and energy +
    gradient (the faster of 1 and all threads) against the Warp kernel on one thread, and a prepared
    scene's energy (a session's evaluation) against the stateless Warp call."""
    n, sp, rows = count(a["n"]), a.get("warp_speedup") or {}, []
    for key, want, what in (("e", 0.8, f"energy at {n}, every joint active: core"),
                            ("eg", 1.0, f"energy + gradient at {n}, every joint active: core"),
                            ("prepared_e", 1.5, f"energy at {n}, every joint active: prepared scene (a session's evaluate)")):
        target = f"{what} vs {WARP} ({'wp.Tape, ' if key == 'eg' else ''}1 thread), throughput"
        if sp.get(key) is None:
            rows.append(_not_measured(6, target, f">= {want:g}x", "Warp peer not run"))
        else:
            rows.append(_at_least(6, target, sp[key], want, "{:.2f}x"))
    return rows


def _all_active_lines(a: dict[str, Any]) -> list[str]:
    modes = [m for m in ("e", "eg", "egh", "psd") if m in a["core"]]
    names = {"e": "energy", "eg": "E+G", "egh": "E+G+H exact", "psd": "E+G+H psd"}
    warp, wsp = a.get("warp") or {}, a.get("warp_speedup") or {}
    ratio = lambda r: _fmt(r, ".2f") + ("x" if r is not None else "")  # noqa: E731
    rows = [[names[m], f"{a['core_1'][m]:.3g}", f"{a['core_threads'][m]:.3g}", _fmt(a["jax"].get(m)),
             ratio(a["speedup"].get(m)), _fmt(warp.get(m)), ratio(wsp.get(m))] for m in modes]
    prepared = a.get("prepared_e") or {}
    if prepared:
        rows.append(["energy, prepared scene (a session)", _fmt(prepared.get("1")),
                     _fmt(prepared.get(str(a["threads"]))), "", "", _fmt(warp.get("e")), ratio(wsp.get("prepared_e"))])
    rows.append(["memory-write floor (E+G+H output)", f"{a['floor_egh']:.3g}", "", "",
                 f"core at {a['floor_fraction_egh']:.0%} of it", "", ""])
    t = all_active_targets(a) + warp_targets(a)
    return [f"{count(a['n'])} joints, half #670 half #669, every one outside its range (each differentiated), "
            "median seconds; ratio: the peer's time / the core's faster of 1 and "
            f"{a['threads']} threads. JAX runs on all cores; Warp on 1 thread (its CPU device has no thread pool), "
            "compile time not counted, energy + gradient by wp.Tape. The energy and E+G calls of the core, "
            "the prepared scene and Warp are timed in turns, one call of each per round, so that every "
            "median spans the same minutes of a shared machine.", "",
            *_table(["mode", "core, 1 thread", f"core, {a['threads']} threads", "JAX jit(vmap), same inputs", "ratio",
                     "Warp CPU, 1 thread", "ratio"], rows), "",
            *_table(["target", "measured", "required", "status"],
                    [[r["target"], r["measured"], r["required"], r["status"]] for r in t])]


def markdown(res: dict[str, Any]) -> str:
    """The whole report as Markdown (every optional section only when its measurement ran)."""
    n = count(res["n_big"])
    lines = [f"# Speed against error (`{res['command']}`)", "", res["machine"], "", f"Scenes: {res['scene']}."]
    lines += _section("Targets", *_target_lines(res))
    lines += _section(f"Speed and error per variant (throughput at {n} joints)", *_variant_lines(res))
    lines += _section("Core in-process, median seconds (joints/s)", *_core_lines(res))
    if res.get("all_active"):
        lines += _section("Every joint active (a mechanism against its stops)", *_all_active_lines(res["all_active"]))
    lines += _section("Peers, median seconds", *_table(
        ["peer", "N", "mode", "s", "joints/s"],
        [[p["peer"], count(p["n"]), p["mode"], f"{p['t']:.3g}", f"{p['n'] / p['t']:.3g}"] for p in res["peers"]]))
    lines += _section("Ratios (core / peer throughput, same run)",
                      *[f"- {k}: **{r:.2f}x**" for k, r in res["ratios"].items()])
    if res.get("http"):
        h = res["http"]
        rows = [[r["encoding"], "yes" if r.get("active_only") else "no", str(r["joints"]), f"{r['requests_per_s']:.3g}",
                 f"{r['joints_per_s']:.3g}", f"{r['p50_ms']:.3g}", f"{r['p99_ms']:.3g}", f"{r['bytes_per_joint']:.0f}"]
                for r in h["rows"]]
        header = ["encoding", "active_only", "joints/request", "requests/s", "joints/s", "p50 ms", "p99 ms",
                  "bytes/joint (both ways)"]
        lines += _section("HTTP on loopback (E+G+H exact, sequential requests, encode + POST + decode)",
                          h.get("note", ""), "", *_table(header, rows))
        for key, what in (("full", "full answer"), ("active_only", "active_only")):
            if f"inprocess_1e4_jps_{key}" in h:
                lines += ["", f"In-process, the same 1e4 request ({what}): {h[f'inprocess_1e4_jps_{key}']:.3g} joints/s; "
                          f"binary HTTP reaches **{h[f'binary_vs_inprocess_1e4_{key}']:.0%}** of it."]
    if res.get("active"):
        a, frac = res["active"], f"{res['active']['fraction']:.0%}"
        lines += _section(
            "Model only what a scene needs (active_only)",
            f"{count(a['n'])} joints, {frac} outside their range, E+G+H exact: full output {a['full']:.3g} s, "
            f"active_only {a['active_only']:.3g} s ({a['full'] / a['active_only']:.1f}x faster). The same scene with "
            f"every joint outside, active_only: {a['all_active']:.3g} s, so the {frac} scene costs "
            f"**{a['active_only'] / a['all_active']:.1%}** of it (ideal: {frac}, plus the energy pass and validation "
            "that every joint needs).")
    if res.get("memory"):
        m = res["memory"]
        lines += _section("Peak memory", f"{count(m['n'])} joints, E+G+H exact: peak {m['peak'] / 2**20:.3g} MiB "
                          f"allocated during the call (tracemalloc) against an output of {m['output'] / 2**20:.3g} "
                          f"MiB: **{m['peak'] / m['output']:.2f}x**.")
    if res.get("sessions"):
        from bench import sessions  # bench/sessions.py: prepared scenes and sessions (it imports this module)

        lines += sessions.section(res["sessions"])
    lines += _section("Notes", *[f"- {t}" for t in res["notes"]])
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------ plot


def label_heights(points: list[tuple[float, float]], gap: float) -> list[float]:
    """log10 heights for the labels of log-log `(x, y)` points, at least `gap` decades apart among points
    whose x lie within a decade of each other (the float64 variants all sit near 1e-14)."""
    lx = [float(np.log10(x)) for x, _ in points]
    ly = [float(np.log10(y)) for _, y in points]
    out = list(ly)
    for i in sorted(range(len(points)), key=lambda i: ly[i]):
        below = [out[j] for j in range(len(points)) if j != i and abs(lx[j] - lx[i]) < 1 and
                 (ly[j], j) < (ly[i], i)]
        out[i] = max([ly[i]] + [h + gap for h in below])
    return out


def plot(res: dict[str, Any], path: Path) -> None:
    """Log-log PNG: E+G+H throughput against Hessian error (well cases), the Pareto front, the floor as a line."""
    import matplotlib

    matplotlib.use("Agg")  # no display: write the file only
    import matplotlib.pyplot as plt

    pts, names = [], []
    for v in res["variants"]:
        if v["name"] != FLOOR and v.get("egh_jps") and (v.get("err") or {}).get("H") is not None:
            pts.append((v["err"]["H"], v["egh_jps"]))
            names.append(v["name"])
    fig, ax = plt.subplots(figsize=(9, 6))
    # The front is over the typical scene's variants: an all-active point is the same code on more work.
    typical = [i for i, name in enumerate(names) if not name.endswith(ALL_ACTIVE)]
    front = [typical[i] for i in pareto([pts[i] for i in typical])]
    ys = [s for _, s in pts]
    heights = label_heights(pts, 0.045 * (np.log10(max(ys) / min(ys)) + 1)) if pts else []
    for i, ((e, s), name, h) in enumerate(zip(pts, names, heights)):
        color = "C3" if i in front else "C0"
        marker = "^" if name.endswith(ALL_ACTIVE) else "o" if name.startswith("core") else "s"
        ax.scatter(e, s, s=60, zorder=3, marker=marker,
                   color="none" if "psd" in name else color, edgecolors=color, linewidths=1.5)
        # Labels to the right, lifted clear of their neighbours; a thin line back to a lifted label's point.
        ax.annotate(name, (e, s), xytext=(e * 2.5, 10**h), fontsize=8, va="bottom",
                    arrowprops=dict(arrowstyle="-", color="0.6", lw=0.5) if h > np.log10(s) + 1e-9 else None)
    if front:
        fx = [pts[i][0] for i in front]
        fy = [pts[i][1] for i in front]
        ax.step(fx, fy, where="post", color="C3", lw=1, ls="--",
                label="Pareto front (best speed for an error budget; red points)")
    floor = next((v for v in res["variants"] if v["name"] == FLOOR and v.get("egh_jps")), None)
    if floor:
        ax.axhline(floor["egh_jps"], color="0.4", lw=1, ls=":", label="memory-write floor (writing the outputs only)")
    warp = next((v for v in res["variants"] if v["name"].startswith(WARP) and v.get("eg_jps")), None)
    if warp:  # no Hessian: its E+G throughput as a line, for scale
        g = (warp.get("err") or {}).get("G")
        ax.axhline(warp["eg_jps"], color="C2", lw=1, ls="-.",
                   label="Warp CPU, E+G only (wp.Tape, 1 thread, all active"
                         + (f"; G error {g:.2g})" if g is not None else ")"))
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.margins(x=0.25)  # room for the labels of the rightmost points
    ax.set_xlabel("max normwise relative error of the Hessian vs the 50-digit reference (well-conditioned cases)")
    ax.set_ylabel(f"E+G+H throughput at {count(res['n_big'])} joints (joints/s)")
    ax.set_title(f"Speed against error ({res['command']})\n"
                 "circles: core, squares: peers, triangles: every joint active; hollow: psd Hessian "
                 "(against the psd reference)", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write(res: dict[str, Any], stem: str, out: Path = RESULTS, with_plot: bool = True) -> list[Path]:
    """`out/stem.md`, `out/stem.json` and (with_plot) `out/stem.png`; the paths written."""
    out.mkdir(parents=True, exist_ok=True)
    md, js, png = out / f"{stem}.md", out / f"{stem}.json", out / f"{stem}.png"
    md.write_text(markdown(res))
    js.write_text(json.dumps(res, indent=1, default=float))
    if not with_plot:
        return [md, js]
    plot(res, png)
    return [md, js, png]
