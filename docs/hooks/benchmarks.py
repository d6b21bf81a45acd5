"""MkDocs hook: the site's Benchmarks page is benchmarks/RESULTS.md itself (one file,
kept beside the scripts that measure it), generated into the site at build time; its
links into docs/ (``../docs/PAGE``, as they work beside the scripts) become the site's."""

from __future__ import annotations

from pathlib import Path

from mkdocs.structure.files import File

RESULTS = Path(__file__).resolve().parents[2] / "benchmarks" / "RESULTS.md"


def on_files(files, config):
    files.append(
        File.generated(
            config, "benchmarks.md", content=RESULTS.read_text().replace("](../docs/", "](")
        )
    )
    return files
