"""Pluggable classes (operators, difference metrics, segmenter methods): a registry of built-in
ones, and `package.module:ClassName` for a user's own."""

from __future__ import annotations

import importlib
from collections.abc import Mapping


def import_class(path: str, base: type, what: str, error: type[Exception]) -> type:
    """The class at import path `package.module:ClassName`, which must subclass `base`.

    Args:
        path: the import path.
        base: the class it must subclass.
        what: the kind in error messages ("operator", "metric", "segmenter method").
        error: the exception raised, with a message naming `path` and what was expected.
    """
    module_name, _, attr = path.partition(":")
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
