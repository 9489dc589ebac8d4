"""Old module paths, kept importable for one release with a deprecation message naming the new place.

The package's layers are folders (``brdfjax.core``, ``brdfjax.runtime``, ``brdfjax.cli``); code written
against the flat layout (``import brdfjax.terms``, ``from brdfjax.errors import InputError``) still runs:
a meta-path finder answers the old name with the new module itself (the same object, so ``isinstance``
and monkeypatching see one class) and warns with :class:`DeprecationWarning`.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

#: old dotted module -> its new place
MOVED = {
    **{f"brdfjax.{m}": f"brdfjax.core.{m}" for m in (
        "geometry", "fields", "distributions", "fresnel", "shadowing", "terms", "presets", "registry", "detector",
        "render")},
    "brdfjax.errors": "brdfjax.runtime.errors",
    "brdfjax.progress": "brdfjax.runtime.progress",
    "brdfjax.compile_cache": "brdfjax.runtime.compile_cache",
    "brdfjax.export_cache": "brdfjax.runtime.export_cache",
    "brdfjax.io.atomic": "brdfjax.runtime.atomic",
    "brdfjax.cli_run": "brdfjax.cli.instrument",
    "brdfjax.fit.cli_fit": "brdfjax.cli.fit",
    "brdfjax.lightcurve.cli": "brdfjax.cli.lightcurve",
    "brdfjax.instrument.raw": "brdfjax.io.raw",
    "brdfjax.sample.cli": "brdfjax.sample.config",
    "brdfjax.diagnose.cli": "brdfjax.diagnose.config",
}

__all__ = ["MOVED", "install"]


class _Alias(importlib.abc.Loader):
    def __init__(self, new: str) -> None:
        self.new = new

    def create_module(self, spec):  # the new module itself stands for the old name
        return importlib.import_module(self.new)

    def exec_module(self, module) -> None:  # already executed under its new name
        pass


class _MovedFinder(importlib.abc.MetaPathFinder):
    def find_spec(self, fullname, path=None, target=None):
        new = MOVED.get(fullname)
        if new is None:
            return None
        warnings.warn(
            f"{fullname} moved to {new}; the old path works for one release", DeprecationWarning, stacklevel=3
        )
        return importlib.util.spec_from_loader(fullname, _Alias(new))


def install() -> None:
    """Put the finder on ``sys.meta_path`` once."""
    if not any(isinstance(f, _MovedFinder) for f in sys.meta_path):
        sys.meta_path.append(_MovedFinder())
