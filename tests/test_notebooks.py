"""The notebooks under notebooks/: each runs top to bottom in SMALL mode, and each is committed stripped.

Every `notebooks/*.ipynb` (picked up by glob, so a new notebook is tested without touching this file) is
executed with nbclient in a kernel running this very interpreter (a throw-away kernelspec, so no other
installed "python3" kernel can be picked up), from the repository root, with `JAXMAP_NB_SMALL=1` and
`JAXMAP_NB_OUT` pointing into a temporary directory. A cell that raises fails the test with its traceback.
"""
from __future__ import annotations

import glob
import json
import os
import re
import sys
import time

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")
pytest.importorskip("ipykernel")

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NOTEBOOKS = sorted(glob.glob(os.path.join(REPO, "notebooks", "*.ipynb")))
IDS = [os.path.basename(p) for p in NOTEBOOKS]
CELL_TIMEOUT_S = 600
SMALL_CELL = re.compile(r"^SMALL\s*=.*os\.environ\.get\(\s*[\"']JAXMAP_NB_SMALL[\"']", re.M)


@pytest.fixture(scope="module")
def kernel_dir(tmp_path_factory):
    """A kernelspec directory whose only kernel is this interpreter with ipykernel."""
    root = tmp_path_factory.mktemp("kernels")
    spec = root / "jaxmap-nb"
    spec.mkdir()
    (spec / "kernel.json").write_text(json.dumps({
        "argv": [sys.executable, "-m", "ipykernel_launcher", "-f", "{connection_file}"],
        "display_name": "jaxmap notebook tests", "language": "python"}))
    return str(root)


def _code_cells(nb):
    return [c for c in nb.cells if c.cell_type == "code"]


def _slowest_cell_s(nb) -> float:
    """Seconds of the slowest executed cell, from the timestamps nbclient records in its metadata."""
    from datetime import datetime

    worst = 0.0
    for c in _code_cells(nb):
        t = c.get("metadata", {}).get("execution", {})
        if "iopub.execute_input" in t and "shell.execute_reply" in t:
            start, end = (datetime.fromisoformat(t[k].replace("Z", "+00:00"))
                          for k in ("iopub.execute_input", "shell.execute_reply"))
            worst = max(worst, (end - start).total_seconds())
    return worst


@pytest.mark.parametrize("path", NOTEBOOKS, ids=IDS)
def test_notebook_is_stripped_and_has_a_small_cell(path):
    nb = nbformat.read(path, as_version=4)
    nbformat.validate(nb)
    for i, cell in enumerate(_code_cells(nb)):
        assert cell.get("outputs") == [] and cell.get("execution_count") is None, (
            f"{IDS[NOTEBOOKS.index(path)]}: code cell {i} has outputs; commit notebooks stripped "
            "(e.g. `jupyter nbconvert --clear-output --inplace notebooks/*.ipynb`)")
    code = _code_cells(nb)
    small = [i for i, c in enumerate(code) if SMALL_CELL.search(c.source)]
    assert small and small[0] < 3, (
        "a `SMALL = os.environ.get(\"JAXMAP_NB_SMALL\", ...)` cell must be among the first three code cells")
    assert any("JAXMAP_NB_OUT" in c.source for c in code), "outputs must go to JAXMAP_NB_OUT when it is set"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=IDS)
def test_notebook_runs_in_small_mode(path, kernel_dir, tmp_path, monkeypatch):
    from jupyter_client.kernelspec import KernelSpecManager
    from jupyter_client.manager import AsyncKernelManager
    from nbclient.exceptions import CellExecutionError

    out = tmp_path / "out"
    monkeypatch.setenv("JAXMAP_NB_SMALL", "1")
    monkeypatch.setenv("JAXMAP_NB_OUT", str(out))
    monkeypatch.setenv("PYDEVD_DISABLE_FILE_VALIDATION", "1")
    nb = nbformat.read(path, as_version=4)
    km = AsyncKernelManager(kernel_name="jaxmap-nb",
                            kernel_spec_manager=KernelSpecManager(kernel_dirs=[kernel_dir],
                                                                  ensure_native_kernel=False))
    client = nbclient.NotebookClient(nb, km=km, timeout=CELL_TIMEOUT_S, resources={"metadata": {"path": REPO}})
    t0 = time.perf_counter()
    try:
        client.execute()
    except CellExecutionError as e:
        pytest.fail(f"{os.path.basename(path)} failed in SMALL mode:\n{e}", pytrace=False)
    elapsed = time.perf_counter() - t0
    print(f"{os.path.basename(path)}: {elapsed:.0f} s in SMALL mode, its slowest cell {_slowest_cell_s(nb):.0f} s "
          f"(timeout {CELL_TIMEOUT_S} s)")
    pngs = sorted(p.name for p in out.glob("*.png"))
    assert pngs, f"{os.path.basename(path)} saved no PNG into JAXMAP_NB_OUT ({out})"
    for p in out.glob("*.png"):
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and p.stat().st_size > 10_000, p
