"""mkdocs hooks: the generated pages (CLI, config keys, equations, validation), the tutorials and the guides' nav.

- ``on_config``: every ``docs/guides/*.md`` not yet in the nav is appended to
  its "Guides" section (pages dropped into the folder appear without editing
  ``mkdocs.yml``); the notebooks are executed into ``docs/tutorials/``
  (:mod:`notebooks`; ``BRDFJAX_DOCS_EXECUTE=0`` copies them unexecuted,
  ``BRDFJAX_DOCS_EXECUTE=keep`` reuses the copies an earlier build executed).
- ``on_files``: the reference pages are generated from the code
  (:mod:`cli_reference`, :mod:`config_reference`, :mod:`equations`) and the
  validation pages from ``experiments/results/`` (:mod:`validation`), with
  their figures; none of them is stored in ``docs/``.
"""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
for p in (str(HERE), str(ROOT)):
    if p not in sys.path:
        sys.path.insert(0, p)

import cli_reference  # noqa: E402
import config_reference  # noqa: E402
import equations  # noqa: E402
import validation  # noqa: E402

import notebooks  # noqa: E402


def _listed(nav: object) -> set[str]:
    if isinstance(nav, str):
        return {nav}
    if isinstance(nav, list):
        return set().union(*(_listed(x) for x in nav)) if nav else set()
    if isinstance(nav, dict):
        return set().union(*(_listed(v) for v in nav.values())) if nav else set()
    return set()


def _title(md: Path) -> str:
    for line in md.read_text(encoding="utf-8").splitlines():
        if line.startswith("# "):
            return line[2:].strip()
    return md.stem.replace("_", " ").replace("-", " ").capitalize()


def on_config(config, **kwargs):
    docs = Path(config["docs_dir"])
    nav = config["nav"]
    guides = next((item for item in nav if isinstance(item, dict) and "Guides" in item), None)
    if guides is not None:
        listed = _listed(nav)
        for md in sorted((docs / "guides").glob("*.md")):
            uri = f"guides/{md.name}"
            if uri not in listed:
                guides["Guides"].append({_title(md): uri})
    mode = os.environ.get("BRDFJAX_DOCS_EXECUTE", "1")
    if mode == "keep":  # reuse executed copies from an earlier build (those missing are copied unexecuted)
        if any(not (notebooks.TARGET / p.name).exists() for p in notebooks.notebooks()):
            notebooks.build(execute=False, only_missing=True)
    else:
        notebooks.build(execute=mode != "0")
    return config


def on_files(files, config, **kwargs):
    from mkdocs.structure.files import File

    pages = {
        "reference/cli.md": cli_reference.page(),
        "reference/config.md": config_reference.page(),
        "physics/equations.md": equations.page(),
    }
    pages.update({f"validation/{slug}.md": validation.page(slug) for slug in validation.PAGES})
    pages["changelog.md"] = (ROOT / "CHANGELOG.md").read_text(encoding="utf-8")
    for uri, text in pages.items():
        files.append(File.generated(config, uri, content=text))
    for fig in validation.figures():
        files.append(File.generated(config, f"figures/{fig.name}", abs_src_path=str(fig)))
    return files


_ROLE = re.compile(r":(?:func|class|mod|meth|attr|data|exc|obj|const|py:[a-z]+):(?=<code>|`)")


def on_post_page(output, page, config, **kwargs):
    """Docstrings use Sphinx cross-reference roles (``:func:`fit```); drop the role, keep the code."""
    return _ROLE.sub("", output)
