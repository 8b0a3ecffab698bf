"""The fast subset's list (conftest.SLOW) names tests that exist, so a rename cannot quietly make a slow test fast."""

from __future__ import annotations

import re
from pathlib import Path

from tests.conftest import SLOW

HERE = Path(__file__).resolve().parent


def test_every_slow_entry_names_an_existing_module_and_test():
    missing = []
    for entry in SLOW:
        module, _, test = entry.partition("::")
        path = next(HERE.glob(f"*/{module}"), HERE / module)  # the modules sit in the layers' folders
        if not path.exists() or (test and not re.search(rf"^(async )?def {re.escape(test)}\(", path.read_text(), re.M)):
            missing.append(entry)
    assert missing == []


def test_the_marker_is_registered():
    text = (HERE.parent / "pyproject.toml").read_text()
    assert re.search(r'markers = \[\s*"slow: ', text)
