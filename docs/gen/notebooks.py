"""The tutorials: the notebooks of ``notebooks/``, executed on a decimated pixel grid, for the docs site.

``python docs/gen/notebooks.py [--step K] [--no-execute]`` writes
``docs/tutorials/<name>.ipynb`` (ignored by git; the mkdocs hook calls
:func:`build` before the site is built).  Each notebook's cell tagged
``parameters`` (it defines ``STEP``, the decimation of full frames) is set
to ``STEP = K``, as ``tests/project/test_notebooks.py`` does; the committed notebooks
stay without outputs.  ``BRDFJAX_DOCS_EXECUTE=0`` copies them unexecuted.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SOURCE = ROOT / "notebooks"
TARGET = ROOT / "docs" / "tutorials"
DOCS_STEP = 16


def notebooks() -> list[Path]:
    return sorted(SOURCE.glob("*.ipynb"))


def build(step: int = DOCS_STEP, execute: bool = True, timeout_s: int = 600, only_missing: bool = False) -> list[Path]:
    """Write every notebook, executed unless ``execute`` is false, into ``docs/tutorials``; the paths written."""
    import nbformat

    TARGET.mkdir(parents=True, exist_ok=True)
    written = []
    for path in notebooks():
        out = TARGET / path.name
        if only_missing and out.exists():
            continue
        nb = nbformat.read(path, as_version=4)
        if execute:
            import nbclient

            for cell in nb.cells:
                if cell.cell_type == "code" and "parameters" in cell.metadata.get("tags", []):
                    cell.source = f"STEP = {step}  # every {step}-th pixel, for the docs build"
            env_path = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
            os.environ["PYTHONPATH"] = env_path  # the kernel imports this checkout
            os.environ.setdefault("MPLBACKEND", "module://matplotlib_inline.backend_inline")
            t0 = time.perf_counter()
            nbclient.NotebookClient(nb, timeout=timeout_s, kernel_name="python3",
                                    resources={"metadata": {"path": str(SOURCE)}}).execute()
            print(f"docs: executed {path.name} at STEP={step} in {time.perf_counter() - t0:.0f} s", file=sys.stderr)
        tmp = out.with_suffix(".tmp")
        nbformat.write(nb, tmp)
        os.replace(tmp, out)
        written.append(out)
    return written


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--step", type=int, default=DOCS_STEP, help="decimation of full frames (default %(default)s)")
    ap.add_argument("--no-execute", action="store_true", help="copy the notebooks without running them")
    a = ap.parse_args()
    build(a.step, execute=not a.no_execute)
