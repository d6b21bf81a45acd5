"""The public API (visvec.api): its docstring's example runs."""

from conftest import ROOT


def test_public_api_docstring_example_runs():
    import os

    from visvec.api import FolderSource, TrianglePipeline, load_rig

    cwd = os.getcwd()
    os.chdir(ROOT)
    try:
        rig = load_rig("configs/triangle.toml")
        rows = list(TrianglePipeline(rig).run(FolderSource("data/sample_frames")))
    finally:
        os.chdir(cwd)
    assert len(rows) == 12 and all(r.ok for r in rows)
