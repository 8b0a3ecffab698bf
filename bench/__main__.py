"""`python -m bench [--quick]`: speed against error of the core, its peers, and the service over HTTP.

Everything is measured in one run on this machine, peers side by side; the report (Markdown,
JSON, PNG) goes to bench/results/ (report.* for the full run, quick.* for --quick). The last
line printed is `speedup_vs_autodiff_egh=<X> speedup_vs_autodiff_e=<Y> speedup_all_active_egh=<Z>
speedup_vs_autodiff_e_all_active=<W> speedup_vs_warp_e=<U> speedup_vs_warp_eg=<V>`:
core / JAX throughput at the largest size (1e5 by default, 1e4 with --quick), E+G+H exact and energy only on the
typical scene, then E+G+H exact and energy on the scene with every joint outside its range (nan
without the JAX peer); then core / Warp throughput on that scene, energy and energy + gradient
(nan without the Warp peer). The core on the faster of 1 thread and all cores, JAX on all cores
(its default), Warp on one thread (its CPU device has no thread pool).
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import platform
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from bench import measure as M
from bench import report
from bench import sessions as S
from bench.scenes import make_scene, shifted
from jointlimits.service.core.heap import keep_heap
from jointlimits.service.core.prepared import prepare

GOLDEN = Path(__file__).resolve().parent.parent / "tests" / "golden_cases.json"
OUTSIDE = 0.1  # fraction of joints past a limit in the timing scenes
ALL_ACTIVE = 1.0  # the hard case beside it: a mechanism pushed against its stops, every joint differentiated
SIZES = [100, 1_000, 10_000, 100_000]
# --quick's sizes: its largest, 1e4, is where its peers and ratios are measured. At 1e5 one JAX E+G+H call takes
# 2.5-4 s here and the quick run makes 13 of them (warm-ups, medians of 5, the all-active scene, the accuracy
# cases), which alone is over a minute; at 1e4 they take ~0.35 s. The ratios are not the 1e5 ones: JAX's time
# per joint grows with the size more than the core's (energy 2.2-2.7 us/joint at 1e4, 4.1 at 3e4, 6 at 1e5 on
# this machine, 2026-11-28), so --quick's figures against JAX read lower than the full run's.
QUICK_SIZES = [100, 1_000, 10_000]
HTTP_SIZES = (10, 1_000, 10_000)  # joints per request, fixed by the issue whatever --sizes says
MODES = ["e", "eg", "egh", "psd"]
THREADS = os.cpu_count() or 1  # JAX's XLA runs on every core by default: the core is timed so too


def log(msg: str) -> None:
    """Progress on stderr: stdout carries the report and, last, the speedup line."""
    print(msg, file=sys.stderr, flush=True)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m bench", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true",
                    help="sizes 100 1000 10000 (unless --sizes), at the largest only energy and E+G+H exact; no psd variants, "
                         "no 'frames precomputed' JAX flavour, no active-only, memory or HTTP; smaller accuracy cases: "
                         "about 30 s on an idle 2-core machine")
    ap.add_argument("--sizes", type=int, nargs="+", default=None, metavar="N",
                    help="core sizes in joints (default: 100 1000 10000 100000, --quick 100 1000 10000); the largest is where peers, "
                         "float32, ratios, active-only and memory are measured, and the full run also times "
                         "energy alone at 10x the largest")
    ap.add_argument("--reps", type=int, default=5, help="timed repetitions per measurement (median; at least 5)")
    ap.add_argument("--no-jax", action="store_true", help="skip the JAX peer (also skipped when JAX is not installed)")
    ap.add_argument("--no-warp", action="store_true", help="skip the Warp peer (also skipped when warp-lang is not installed)")
    ap.add_argument("--no-http", action="store_true", help="skip the HTTP measurements")
    ap.add_argument("--no-sessions", action="store_true", help="skip prepared scenes and sessions (bench/sessions.py)")
    ap.add_argument("--sessions-only", action="store_true",
                    help="only prepared scenes vs stateless (in-process at --sizes) and sessions vs HTTP (loopback, "
                         "unless --no-http); writes DIR/sessions.md and .json")
    ap.add_argument("--no-plot", action="store_true", help="write no PNG (also skipped when matplotlib is missing)")
    ap.add_argument("--out", type=Path, default=report.RESULTS, metavar="DIR",
                    help="directory of the report files (default: bench/results)")
    return ap.parse_args(argv)


def command(args: argparse.Namespace) -> str:
    """The command line of this run, less --out (where it writes does not change what it measured)."""
    flags = [f for f in ("quick", "no_jax", "no_warp", "no_http", "no_plot", "no_sessions", "sessions_only") if getattr(args, f)]
    words = ["python -m bench"] + ["--" + f.replace("_", "-") for f in flags]
    if args.sizes is not None and sorted(set(args.sizes)) != (QUICK_SIZES if args.quick else SIZES):
        words.append("--sizes " + " ".join(str(n) for n in sorted(set(args.sizes))))
    if args.reps != 5:
        words.append(f"--reps {args.reps}")
    return " ".join(words)


def case_list(quick: bool) -> list[tuple[str, str, dict]]:
    """Golden cases + generated ones (well) + hard ones (strongly affine, large steps, far from the origin)."""
    cases = M.golden_cases(GOLDEN)
    k = 1 if quick else 3  # the reference is mpmath at 50 digits: a few ms per joint
    gens = [("generated_rigidish", "well", dict(n_joints=16 * k, outside=0.6, seed=11)),
            ("hard_strain_0.3", "hard", dict(n_joints=8 * k, outside=0.6, seed=12, strain=0.3)),
            ("hard_large_step", "hard", dict(n_joints=8 * k, outside=0.6, seed=13, step=0.9))]
    for name, fam, kw in gens:
        cases.append((name, fam, M.to_request(*make_scene(**kw))))
    cases.append(("hard_far_1e4", "hard", M.to_request(*shifted(*make_scene(8 * k, outside=0.6, seed=14), 1e4))))
    return cases


def load_jax(res: dict[str, Any], no_jax: bool) -> tuple[Any, list[tuple[str, bool]], str]:
    """The JAX peer class (None if skipped or missing, which is noted), its flavours, and why it is absent."""
    if no_jax:
        return None, [], "skipped (--no-jax)"
    try:
        import jax

        from bench.peer_jax import FLAVOURS, JaxPeer
    except ImportError:
        res["notes"].append("JAX peer: not installed (pip install -e '.[bench]'); its rows and targets are absent.")
        return None, [], "JAX not installed"
    res["jax_version"] = jax.__version__
    return JaxPeer, FLAVOURS, ""


def load_warp(res: dict[str, Any], no_warp: bool) -> Any:
    """The Warp peer class (None if skipped or missing, which is noted)."""
    if no_warp:
        return None
    try:
        import warp

        from bench.peer_warp import WarpPeer
    except ImportError:
        res["notes"].append("Warp peer: not installed (pip install -e '.[bench]'); its rows and targets are absent.")
        return None
    res["warp_version"] = warp.__version__
    return WarpPeer


def time_jax(JaxPeer: Any, flavours: list[tuple[str, bool]], scene: tuple, quick: bool, reps: int,
             res: dict[str, Any]) -> dict[tuple[str, str], float]:
    """Median seconds of each JAX flavour on `scene` per bench mode ("psd": the psd E+G+H)."""
    t: dict[tuple[str, str], float] = {}
    n = sum(j.body_ids.shape[0] for j in scene[1])
    for name, same in flavours:
        for psd in (False,) if quick else (False, True):
            peer = JaxPeer(*scene, same_work=same, psd=psd)
            for m in ["egh"] if psd else (["e", "egh"] if quick else ["e", "eg", "egh"]):
                key = "psd" if psd else m
                t[(name, key)] = M.median_time(lambda p=peer, m=m: p(m), reps)
                res["peers"].append({"peer": name, "n": n, "mode": M.MODE_NAMES[key], "t": t[(name, key)]})
                log(f"{name} {key}: {t[(name, key)]:.4g}s")
            del peer  # a 1e5 peer holds its inputs on the device
    return t


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    quick, reps = args.quick, max(5, args.reps)
    sizes = sorted(set(args.sizes or (QUICK_SIZES if quick else SIZES)))
    if args.sessions_only:
        return S.only(command(args), sizes, reps, args.out, with_wire=not args.no_http)
    n_big = sizes[-1]
    t_start = time.perf_counter()
    res: dict[str, Any] = {"command": command(args), "n_big": n_big,
                           "notes": [], "targets": [], "peers": [], "variants": []}
    JaxPeer, flavours, jax_missing = load_jax(res, args.no_jax)
    WarpPeer = load_warp(res, args.no_warp)
    flavours = flavours[:1] if quick else flavours
    with_plot = not args.no_plot and importlib.util.find_spec("matplotlib") is not None
    if not args.no_plot and not with_plot:
        res["notes"].append("Plot: matplotlib not installed (pip install -e '.[bench]'); no PNG written.")
    res["machine"] = (f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, Python "
                      f"{platform.python_version()}, NumPy {np.__version__}, JAX {res.get('jax_version', '-')}, "
                      f"Warp {res.get('warp_version', '-')}; "
                      f"medians of {reps} repetitions after one warm-up")
    if quick:
        res["notes"].append(f"--quick: sizes {', '.join(report.count(n) for n in sizes)}; peers, ratios and the all-active "
                            f"scene at {report.count(n_big)} (the full run's are at 1e5, where JAX's time per joint is "
                            "higher: its ratios read lower here).")
    res["scene"] = (f"half #670 half #669, {OUTSIDE:.0%} of joints outside their range (5% for active-only); "
                    f"beside it at the largest size, every joint outside ({ALL_ACTIVE:.0%}, 'all active')")

    # ---------------------------------------------------------------- core in-process
    res["core_modes"] = [M.MODE_NAMES[m] for m in MODES]
    scenes = {n: make_scene(n, OUTSIDE, seed=n % 97) for n in sizes}
    # First with glibc's default heap (every large array a fresh mapping, faulted in on each call),
    # then as the service runs: `keep_heap`, which reuses freed pages as JAX's allocator does.
    t_default_heap = {m: M.median_time(M.core_call(*scenes[n_big], m), reps) for m in ("e", "egh")}
    res["notes"].append(f"glibc's default heap, 1 thread, at {report.count(n_big)}: energy {t_default_heap['e']:.3g} s, "
                        f"E+G+H exact {t_default_heap['egh']:.3g} s; every other core figure is with keep_heap "
                        f"({'applied' if keep_heap() else 'not available here'}), as `jointlimits serve` runs.")
    log(res["notes"][-1])
    core: dict[str, list[float | None]] = {}
    for n in sizes:
        # --quick: only the two modes of the final line at the largest size.
        keep = [m for m in MODES if not (quick and n == n_big and m in ("eg", "psd"))]
        core[str(n)] = [M.median_time(M.core_call(*scenes[n], m), reps) if m in keep else None for m in MODES]
        log(f"core N={n}: " + ", ".join(f"{m}={t:.4g}s" for m, t in zip(MODES, core[str(n)]) if t))
    if not quick:  # energy alone at 10x: a scene too large for the Hessian's 4.6 KB per joint
        n_e = 10 * n_big
        core[str(n_e)] = [M.median_time(M.core_call(*make_scene(n_e, OUTSIDE, seed=1), "e"), reps), None, None, None]
        log(f"core N={n_e}: e={core[str(n_e)][0]:.4g}s")
    res["core"] = core
    t_core = dict(zip(MODES, core[str(n_big)]))
    # The same calls on every core (`threads`: bitwise the same answers).
    t_mt = {m: M.median_time(M.core_call(*scenes[n_big], m, threads=THREADS), reps)
            for m in (["e", "egh"] if quick else ["e", "egh", "psd"])} if THREADS > 1 else dict(t_core)
    res["threads"] = THREADS
    log(f"core N={n_big}, {THREADS} threads: " + ", ".join(f"{m}={t:.4g}s" for m, t in t_mt.items()))

    # ---------------------------------------------------------------- peers
    big = scenes[n_big]
    t_peer = time_jax(JaxPeer, flavours, big, quick, reps, res) if JaxPeer else {}
    n_loop = min(100 if quick else 300, n_big)
    loop_scene = make_scene(n_loop, OUTSIDE, seed=5)
    for m in ("e", "egh"):
        t = M.median_time(M.loop_call(*loop_scene, m), reps)
        t_peer[("loop", m)] = t * n_big / n_loop  # the per-joint cost is constant: scaled to n_big
        res["peers"].append({"peer": "per-joint Python loop", "n": n_loop, "mode": M.MODE_NAMES[m], "t": t})
    for n in sizes:
        for m in ("e", "egh"):
            t = M.median_time(M.floor_call(n, m), reps)
            res["peers"].append({"peer": report.FLOOR, "n": n, "mode": M.MODE_NAMES[m], "t": t})
            t_peer[("floor", m)] = t  # the last, n_big, stays
    t32 = {m: M.median_time(M.core_call(*big, m, dtype=np.float32), reps) for m in ("e", "egh")}
    log(f"float32: {t32}")

    # ---------------------------------------------------------------- accuracy
    cases = case_list(quick)
    cs = M.build_case_set(cases, modes=("exact",) if quick else ("exact", "psd"))
    n_well = sum(f == "well" for f in cs.families)
    res["notes"].append(f"Accuracy over {len(cases)} cases ({n_well} well-conditioned: the golden cases and generated "
                        f"ones; {len(cases) - n_well} hard: strain 0.3, steps of 0.9 rad, a scene 1e4 from the "
                        "origin), against bench/reference.py (mpmath, 50 digits).")

    def variant(name: str, egh_t: float | None, e_t: float | None, results: M.Results | None,
                mode: str = "exact") -> None:
        """A row of speed (joints/s at n_big) and error (per family) for the table and the plot."""
        res["variants"].append({
            "name": name, "egh_jps": n_big / egh_t if egh_t else None, "e_jps": n_big / e_t if e_t else None,
            "err": cs.errors(results, mode, "well") if results is not None else None,
            "err_hard": cs.errors(results, mode, "hard") if results is not None else None,
        })

    variant(report.CORE, t_core["egh"], t_core["e"], M.core_results(cs, "exact"))
    if THREADS > 1:
        variant(report.core_threads(THREADS), t_mt["egh"], t_mt["e"], M.core_results(cs, "exact", threads=THREADS))
    if not quick:
        variant("core float64 psd", t_core["psd"], None, M.core_results(cs, "psd"), "psd")
    variant("core float32 exact", t32["egh"], t32["e"], M.core_results(cs, "exact", np.float32))
    variant("per-joint loop", t_peer[("loop", "egh")], t_peer[("loop", "e")],
            M.loop_results(cs.bodies, M.single_joints(cs.batches)))
    big_rows = {j.constitution_uid: j.body_ids.shape[0] for j in big[1]}  # the shapes JAX compiled for
    for name, same in flavours:
        for psd in (False,) if quick else (False, True):
            key = "psd" if psd else "egh"
            results = JaxPeer(cs.bodies, cs.batches, same_work=same, psd=psd).results(pad_to=big_rows)
            variant(name + (" psd" if psd else ""), t_peer.get((name, key)), None if psd else t_peer.get((name, "e")),
                    results, "psd" if psd else "exact")
    if WarpPeer is not None:
        # Energy and gradient only (no Hessian: its error is n/a); its speed is the all-active scene's (below).
        warp_results = WarpPeer(cs.bodies, cs.batches).results()
        res["warp_error"] = {"err": cs.errors(warp_results, "exact", "well"),
                             "err_hard": cs.errors(warp_results, "exact", "hard")}
    variant(report.FLOOR, t_peer[("floor", "egh")], t_peer[("floor", "e")], None)

    # ---------------------------------------------------------------- ratios and extras
    n_s = report.count(n_big)
    ratios: dict[str, float] = {}
    for name, _ in flavours:
        for label, t in (("1 thread", t_core), (f"{THREADS} threads", t_mt)) if THREADS > 1 else (("1 thread", t_core),):
            ratios[f"E+G+H exact, {n_s}, core on {label} vs {name}"] = t_peer[(name, "egh")] / t["egh"]
            ratios[f"energy, {n_s}, core on {label} vs {name}"] = t_peer[(name, "e")] / t["e"]
    if not quick and flavours:
        ratios[f"E+G+H psd, {n_s}, core on {THREADS} threads vs {flavours[0][0]} psd"] = (
            t_peer[(flavours[0][0], "psd")] / t_mt["psd"])
    ratios[f"E+G+H exact, {n_s}, vs per-joint loop"] = t_peer[("loop", "egh")] / t_core["egh"]
    ratios[f"E+G+H exact, {n_s}, vs memory-write floor"] = t_peer[("floor", "egh")] / t_core["egh"]
    res["ratios"] = ratios
    jname = report.JAX
    # The core as a user would run it: the faster of 1 thread and all cores, per mode (JAX runs on all cores).
    res["best_threads"] = {m: 1 if t_core[m] <= t_mt[m] else THREADS for m in ("egh", "e")}
    t_best = {m: min(t_core[m], t_mt[m]) for m in ("egh", "e")}
    res["speedup"] = {m: (t_peer[(jname, m)] / t_best[m] if (jname, m) in t_peer else None) for m in ("egh", "e")}

    res["all_active"] = _all_active(JaxPeer, WarpPeer, n_big, quick, reps)
    _all_active_variants(res)
    if not quick:
        res["active"] = _active_only(n_big, reps)
        log(f"active: {res['active']}")
        res["memory"] = _memory(big)
        log(f"memory: {res['memory']}")
        if not args.no_http:
            res["http"] = _http(reps)
        if not args.no_sessions:
            res["sessions"] = S.run(sizes, reps, with_wire=not args.no_http)
    res["targets"] = report.targets(res, jax_missing or "JAX peer not run")
    res["targets"] += report.warp_targets(res["all_active"])
    if res.get("sessions"):
        res["targets"] += S.targets(res["sessions"])
    res["seconds"] = time.perf_counter() - t_start
    res["notes"].append(f"This run took {res['seconds']:.0f} s.")
    files = report.write(res, "quick" if quick else "report", args.out, with_plot)
    log("wrote " + ", ".join(str(f) for f in files))
    print(report.markdown(res))
    print(speedup_line(res["speedup"], res["all_active"]["speedup"], res["all_active"].get("warp_speedup")))
    return 0


def speedup_line(speedup: dict[str, float | None], all_active: dict[str, float | None] | None = None,
                 warp: dict[str, float | None] | None = None) -> str:
    """The run's last line: core / JAX and core / Warp throughput at the largest size, nan where a peer did not run."""
    nan = float("nan")
    x, y = (nan if speedup.get(m) is None else speedup[m] for m in ("egh", "e"))
    z, w = ((all_active or {}).get(m) for m in ("egh", "e"))
    u, v = ((warp or {}).get(m) for m in ("e", "eg"))
    f = lambda a: nan if a is None else a  # noqa: E731
    return (f"speedup_vs_autodiff_egh={x:.2f} speedup_vs_autodiff_e={y:.2f} "
            f"speedup_all_active_egh={f(z):.2f} speedup_vs_autodiff_e_all_active={f(w):.2f} "
            f"speedup_vs_warp_e={f(u):.2f} speedup_vs_warp_eg={f(v):.2f}")


def _all_active(JaxPeer: Any, WarpPeer: Any, n: int, quick: bool, reps: int) -> dict[str, Any]:
    """Every joint outside its range at `n` joints: the core (1 thread and all cores), JAX (its fair flavour),
    Warp (1 thread), a prepared scene's energy (a session's evaluation) and the memory-write floor, median
    seconds per mode; ratios of throughput, core at its faster thread count."""
    scene = make_scene(n, ALL_ACTIVE, seed=n % 89)
    modes = ["e", "eg", "egh"] if quick else ["e", "eg", "egh", "psd"]
    # The energy and E+G calls the Warp targets compare, in turns with Warp's own (`M.median_times`): the
    # core on 1 and on every thread, a session's energy (the scene prepared once, q_ref and q_prev work
    # done: each call forms the step to q), and Warp on one thread.
    fast = [m for m in modes if m in ("e", "eg")]
    threads = sorted({1, THREADS})
    calls: dict[tuple[str, Any], Callable[[], Any]] = {}
    for th in threads:
        calls |= {(f"core {th}", m): M.core_call(*scene, m, threads=th) for m in fast}
    for th in threads:
        ps = prepare(scene[0], scene[1], threads=th)
        calls[("prepared", th)] = lambda ps=ps: ps.evaluate(scene[0].q, outputs=("energy",))
    warp_peer = WarpPeer(*scene) if WarpPeer is not None else None  # compiles (or loads from Warp's cache) and runs once: not timed
    if warp_peer is not None:
        calls |= {("warp", m): (lambda m=m: warp_peer(m)) for m in ("e", "eg")}
    t = M.median_times(calls, reps)
    del calls, warp_peer
    slow = [m for m in modes if m not in fast]
    for th in threads:
        t |= {(f"core {th}", m): M.median_time(M.core_call(*scene, m, threads=th), reps) for m in slow}
    core1 = {m: t[("core 1", m)] for m in modes}
    coreT = {m: t[(f"core {THREADS}", m)] for m in modes}
    core = {m: min(core1[m], coreT[m]) for m in modes}
    log(f"all active N={n}: core 1 thread {core1}, {THREADS} threads {coreT}")
    prepared = {th: t[("prepared", th)] for th in threads}
    log(f"all active N={n}: prepared energy {prepared}")
    jax: dict[str, float] = {}
    if JaxPeer is not None:
        for psd in (False,) if quick else (False, True):
            peer = JaxPeer(*scene, same_work=True, psd=psd)
            for m in ["egh"] if psd else ["e", "egh"] if quick else ["e", "eg", "egh"]:
                jax["psd" if psd else m] = M.median_time(lambda p=peer, m=m: p(m), reps)
            del peer
        log(f"all active N={n}: JAX {jax}")
    warp = {m: t[("warp", m)] for m in ("e", "eg") if ("warp", m) in t}
    if warp:
        log(f"all active N={n}: Warp (1 thread) {warp}")
    floor = M.median_time(M.floor_call(n, "egh"), reps)
    t_prep = min(prepared.values())
    return {"n": n, "fraction": ALL_ACTIVE, "core_1": core1, "core_threads": coreT, "core": core, "jax": jax,
            "floor_egh": floor, "threads": THREADS, "warp": warp, "warp_threads": 1,
            "prepared_e": {str(k): t for k, t in prepared.items()},
            "speedup": {m: (jax[m] / core[m] if m in jax else None) for m in modes},
            "warp_speedup": {"e": warp["e"] / core["e"], "eg": warp["eg"] / core["eg"],
                             "prepared_e": warp["e"] / t_prep} if warp else {},
            "floor_fraction_egh": floor / core["egh"],
            "psd_over_exact": core["psd"] / core["egh"] if "psd" in core else None}


def _all_active_variants(res: dict[str, Any]) -> None:
    """The all-active timings as variants (table and plot), each with the error of its typical-scene twin:
    the accuracy cases do not depend on the timing scene."""
    a, n = res["all_active"], res["n_big"]
    by_name = {v["name"]: v for v in res["variants"]}
    pairs = [(report.CORE, a["core"], "egh", "e"), ("core float64 psd", a["core"], "psd", None),
             (report.JAX, a["jax"], "egh", "e"), (report.JAX + " psd", a["jax"], "psd", None)]
    if a.get("warp") and res.get("warp_error"):  # energy and E+G only: no E+G+H column, no Hessian error
        res["variants"].append({"name": report.WARP + report.ALL_ACTIVE, "egh_jps": None, "eg_jps": n / a["warp"]["eg"],
                                "e_jps": n / a["warp"]["e"], **res["warp_error"]})
        for m in ("e", "eg"):
            res["peers"].append({"peer": report.WARP + " (1 thread)", "n": n,
                                 "mode": "energy" if m == "e" else "E+G (wp.Tape)", "t": a["warp"][m]})
    for name, t, m, me in pairs:
        twin = by_name.get(name)
        if twin is None or m not in t:
            continue
        res["variants"].append({"name": name + report.ALL_ACTIVE, "egh_jps": n / t[m],
                                "e_jps": n / t[me] if me else None, "err": twin["err"], "err_hard": twin["err_hard"]})


def _active_only(n: int, reps: int) -> dict[str, Any]:
    """E+G+H exact with and without active_only on a 5%-outside scene, and active_only with every joint outside."""
    def call(frac: float, active_only: bool) -> Callable:
        return M.core_call(*make_scene(n, frac, seed=3), "egh", active_only=active_only)

    return {"n": n, "fraction": 0.05, "full": M.median_time(call(0.05, False), reps),
            "active_only": M.median_time(call(0.05, True), reps), "all_active": M.median_time(call(1.0, True), reps)}


def _memory(scene: tuple) -> dict[str, int]:
    """Peak bytes during one E+G+H exact call on `scene` against the bytes of what it returns."""
    n = sum(j.body_ids.shape[0] for j in scene[1])
    peak = M.peak_memory(M.core_call(*scene, "egh"))
    return {"n": n, "peak": peak, "output": M.output_bytes(n, "egh") + 8 * n}  # + the int64 index column


def _http(reps: int) -> dict[str, Any]:
    """JSON and binary requests at HTTP_SIZES against a local server, full answers and active_only;
    at 1e4 each binary flavour against the same request in-process."""
    from bench import http_bench as H

    rows = []
    with H.Server() as srv:
        binary = H.binary_available(srv.url, *make_scene(10, OUTSIDE, seed=1))
        for n in HTTP_SIZES:
            scene = make_scene(n, OUTSIDE, seed=7)
            for enc in ["json", "binary"] if binary else ["json"]:
                for active_only in (False, True):
                    # Small requests are noisy and cheap: more of them.
                    r = H.measure(srv.url, *scene, enc == "binary", reps if n > 10 else 50, active_only)
                    r.update(encoding=enc, active_only=active_only)
                    rows.append(r)
                    log(f"http {enc} {n} active_only={active_only}: {r}")
    out: dict[str, Any] = {"rows": rows, "note": "binary: application/msgpack" if binary else "binary: not available"}
    scene = make_scene(10_000, OUTSIDE, seed=7)
    for r in rows:
        if r["encoding"] == "binary" and r["joints"] == 10_000:
            # In-process on the very request sent over HTTP, so only the transport differs.
            key = "active_only" if r["active_only"] else "full"
            t = M.median_time(M.core_call(*scene, "egh", active_only=r["active_only"]), reps)
            out[f"inprocess_1e4_jps_{key}"] = 10_000 / t
            out[f"binary_vs_inprocess_1e4_{key}"] = r["joints_per_s"] / out[f"inprocess_1e4_jps_{key}"]
    return out


if __name__ == "__main__":
    raise SystemExit(main())
