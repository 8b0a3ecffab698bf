"""The HTTP API page's example (docs/http-api.md, moved from the README), run and compared as text: the curl
example's printed answer is the server's."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import httpx

from tests.conftest import same_numbers
from tests.http.test_contract_live import live  # noqa: F401 (fixture)

README = (Path(__file__).resolve().parents[2] / "docs" / "http-api.md").read_text()


def example_section() -> str:
    return README.split("## Example\n", 1)[1].split("\n## ", 1)[0]


def curl_example() -> tuple[str, dict[str, str], bytes]:
    """Path, headers and body of the page's curl command."""
    cmd = example_section().split("```bash\n", 1)[1].split("```", 1)[0]
    argv = shlex.split(cmd)
    assert argv[:2] == ["curl", "-s"], argv
    url = argv[2]
    headers = dict(h.split(": ", 1) for flag, h in zip(argv, argv[1:]) if flag == "-H")
    body = argv[argv.index("-d") + 1].encode()
    return re.sub(r"^(https?://)?localhost:8000", "", url), headers, body


def printed_answer() -> str:
    return example_section().split("```json\n", 1)[1].split("```", 1)[0].strip()


def test_the_curl_example_prints_what_the_server_sends(live):
    path, headers, body = curl_example()
    r = httpx.post(live + path, headers=headers, content=body)
    assert r.status_code == 200, r.text
    assert same_numbers(r.text, printed_answer()), r.text  # as text, the floats up to another CPU's last bits
