"""The `jointlimits` command: `serve` is the service's (`service/cli.py`), `evaluate` the SDK's
(`client/robot_cli.py`). One entry point over both sits here, where the namespace joins the two folders,
so that the service never imports the SDK; each side is imported only when its command runs."""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence


def main(argv: Sequence[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if args[:1] == ["evaluate"]:
        from jointlimits.client.robot_cli import main as evaluate

        try:
            return evaluate(args[1:])
        except BrokenPipeError:  # `jointlimits evaluate ... --json | head`: the reader left; no traceback
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # Python's recipe: exit's flush goes nowhere
            return 1
    from jointlimits.service.cli import main as service

    return service(args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
