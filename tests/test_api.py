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


def test_every_export_is_documented_with_its_parameters_or_attributes():
    """Every class and function `visvec.api` exports has a numpydoc Parameters (or,
    for a class of values, Attributes) section: what a script passes and gets, with
    units."""
    import inspect

    import visvec.api as api

    bare = [n for n in api.__all__
            if (inspect.isclass(getattr(api, n)) or callable(getattr(api, n)))
            and not any(k in (inspect.getdoc(getattr(api, n)) or "")
                        for k in ("Parameters\n---", "Attributes\n---"))]  # fmt: skip
    assert bare == []
