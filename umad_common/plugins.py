"""Pluggable kinds (difference metrics, segmenter methods): a registry of built-in classes, and
`package.module:ClassName` for a user's own."""

from __future__ import annotations

import importlib
from collections.abc import Mapping


def registered_class(name: str, registry: Mapping[str, type], base: type, what: str, error: type[Exception]) -> type:
    """The class registered as `name`, or imported from a `package.module:ClassName` path.

    Args:
        name: a registered name or an import path.
        registry: the built-in classes by name.
        base: the class an imported one must subclass.
        what: the kind in error messages ("metric", "segmenter method").
        error: the exception raised, with a message naming `name` and what was expected.
    """
    if name in registry:
        return registry[name]
    module_name, _, attr = name.partition(":")
    if not attr:
        raise error(f"unknown {what} {name!r}; expected one of {sorted(registry)} or `package.module:ClassName`")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise error(f"cannot import module {module_name!r} for {what} {name!r}: {exc}") from None
    cls = getattr(module, attr, None)
    if not (isinstance(cls, type) and issubclass(cls, base)):
        raise error(f"{what} {name!r}: expected a {base.__name__} subclass, got {cls!r}")
    return cls
