"""`jointlimits evaluate ROBOT.urdf Q...`: a robot's joints against their limits, one line per joint.

The positions come in the order `jointlimits evaluate ROBOT.urdf` lists (no positions: that list), or
from a JSON file (`--request`) `{"q": [...] or {"name": position}, "q_prev": ..., "reference": ...,
"strength": ...}`. Evaluated in this process, or by a server with `--url`. `--json` prints the readings
as a JSON list for scripts; `--plot FILE.png` draws them (the `plot` extra).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import warnings
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="jointlimits evaluate",
                                description="Each joint of a URDF robot at a joint vector: position, limits, energy.")
    p.add_argument("robot", help="the URDF file")
    p.add_argument("q", nargs="*", type=float, help="one position (rad, m) per moving joint, as listed without q")
    p.add_argument("--request", metavar="FILE", help='a JSON file {"q": ..., "q_prev": ..., "reference": ..., "strength": ...}')
    p.add_argument("--strength", type=float, help="every limit's strength (default: the constitutions' 1)")
    p.add_argument("--url", help="evaluate on this server (default: in this process)")
    p.add_argument("--json", action="store_true", help="print the readings as JSON")
    p.add_argument("--plot", metavar="PNG", help="also draw each joint's position inside its range to this file")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from jointlimits.client import Client, LocalClient, ServiceError
    from jointlimits.client.robot import Robot, plot

    try:
        with warnings.catch_warnings():  # what is not modelled is printed below, with the readings
            warnings.simplefilter("ignore")
            robot = Robot.load(args.robot)
        given: dict[str, Any] = json.loads(Path(args.request).read_text()) if args.request else {}
        if not isinstance(given, dict):
            raise ValueError(f"{args.request}: a JSON object is expected, got {type(given).__name__}")
        if not args.q and not given:
            print(f"{args.robot}: {len(robot.names)} moving joints, give one position each: {' '.join(robot.names)}"
                  + "".join(f"\nnot modelled: {note}" for note in robot.unmodelled))
            return 0
        if args.q and given.get("q") is not None:
            raise ValueError("give the positions either on the command line or in --request, not both")
        q = given.pop("q", None) if not args.q else args.q
        if args.strength is not None:
            given["strength"] = args.strength
        unknown = sorted(set(given) - {"q_prev", "reference", "strength"})
        if unknown or q is None:
            raise ValueError(f"{args.request}: needs 'q', may have 'q_prev', 'reference', 'strength'; got {unknown}")
        request = robot.request(q, **given)
    except (ImportError, OSError, ValueError) as e:  # no yourdfpy, a file that does not read, positions that do not fit
        where = f"{args.request}: " if isinstance(e, json.JSONDecodeError) else ""  # json's words name no file
        print(f"jointlimits evaluate: {where}{e}", file=sys.stderr)
        return 2
    try:
        with Client(args.url) if args.url else LocalClient() as client:
            readings = robot.readings(client.evaluate(request), q)
        if args.plot:  # no matplotlib, a picture that cannot be written: said as the server's faults are
            plot(readings, args.plot, title=f"{robot.urdf.robot.name} at the given joint vector")
    except (ServiceError, ImportError, OSError) as e:  # a server not there, busy or refusing: its words, no traceback
        loc = getattr(e, "loc", None) or ()  # a fault at ("body", "batches", b, field, row): say the joint's name
        name = next((n for n, h in robot.handles.items() if loc[2:5:2] == (h.batch, h)), None) if len(loc) > 4 else None
        print(f"jointlimits evaluate: {f'joint {name}: ' if name else ''}{e}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps([asdict(r) for r in readings], indent=1))
        return 0
    unit = lambda r: "m" if r.type == "prismatic" else "rad"  # noqa: E731
    rows = [(r.name, f"{r.position:.6g} {unit(r)}",
             "no limit" if r.lower is None else f"[{r.lower:.6g}, {r.upper:.6g}]",
             f"{r.energy:.6g}", "ACTIVE" if r.active else "") for r in readings]
    widths = [max([len(h), *(len(row[k]) for row in rows)]) for k, h in enumerate(HEADER)]  # no rows: the header's
    for row in (HEADER, *rows):
        print("  ".join(c.ljust(w) for c, w in zip(row, widths)).rstrip())
    total = math.fsum(r.energy for r in readings)
    print(f"total energy {total:.6g}; {sum(r.active for r in readings)} active of {len(readings)} joints"
          + "".join(f"\nnot modelled: {note}" for note in robot.unmodelled))
    return 0


HEADER = ("joint", "position", "limits", "energy", "active")
