"""Pluggable classes (operators, difference metrics, segmenter methods): a registry of built-in
ones, and `package.module:ClassName` for a user's own."""

from __future__ import annotations

import importlib
import logging
import re
from collections.abc import Mapping

# The repository's folders operators/ and replay/ install under UMAD's own import names; an import
# path with the old name still loads, with a one-line notice naming the new one.
RENAMED_PACKAGES = {"operators": "umad_operators", "replay": "umad_replay"}

log = logging.getLogger("umad.plugins")
_noticed: set[str] = set()  # old import paths this process has named in a notice (a graph is validated often)


def current_import_path(path: str, what: str) -> str:
    """`path` with a renamed package's old name replaced by its new one, and a one-line notice saying
    so (once per path and process)."""
    package = re.split(r"[.:]", path, maxsplit=1)[0]
    if package not in RENAMED_PACKAGES:
        return path
    renamed = RENAMED_PACKAGES[package] + path[len(package) :]
    if path in _noticed:
        return renamed
    _noticed.add(path)
    log.warning(
        "%s %r: deprecated, package %r is now %r; use %r", what, path, package, RENAMED_PACKAGES[package], renamed
    )
    return renamed


def import_class(path: str, base: type, what: str, error: type[Exception]) -> type:
    """The class at import path `package.module:ClassName`, which must subclass `base`.

    Args:
        path: the import path.
        base: the class it must subclass.
        what: the kind in error messages ("operator", "metric", "segmenter method").
        error: the exception raised, with a message naming `path` and what was expected.
    """
    module_name, _, attr = current_import_path(path, what).partition(":")
    if not attr:
        raise error(f"{what} {path!r}: expected an import path `package.module:ClassName`")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise error(f"cannot import module {module_name!r} for {what} {path!r}: {exc}") from None
    cls = getattr(module, attr, None)
    if not (isinstance(cls, type) and issubclass(cls, base)):
        raise error(f"{what} {path!r}: expected a {base.__name__} subclass, got {cls!r}")
    return cls


def registered_class(
    name: str, registry: Mapping[str, type | str], base: type, what: str, error: type[Exception]
) -> type:
    """The class registered as `name`, or imported from a `package.module:ClassName` path (see
    `import_class`, whose arguments these are besides `registry`: the built-in classes by name; a
    built-in whose module is slow to import, e.g. one that needs torch, is registered by its import
    path and imported on first use, so every process that merely checks a graph does not pay for it)."""
    if name in registry:
        entry = registry[name]
        return entry if isinstance(entry, type) else import_class(entry, base, what, error)
    if ":" not in name:
        raise error(f"unknown {what} {name!r}; expected one of {sorted(registry)} or `package.module:ClassName`")
    return import_class(name, base, what, error)
