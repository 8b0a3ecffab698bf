"""MkDocs hook: the committed bench plot (bench/results/report.png) joins the site as bench/report.png.

The docs show the committed run's figure itself rather than a copy in docs/ that could drift from it.
"""

from __future__ import annotations

from pathlib import Path

from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parent.parent
EXTRA = {"bench/report.png": ROOT / "bench" / "results" / "report.png"}


def on_files(files: Files, config) -> Files:
    for uri, src in EXTRA.items():
        files.append(File.generated(config, uri, abs_src_path=str(src)))
    return files
