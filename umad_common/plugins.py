"""The one import-path loader: every pluggable kind (operators, difference metrics) also accepts a
class of the user's own as `package.module:ClassName`."""

from __future__ import annotations

import importlib
from typing import TypeVar

T = TypeVar("T")


def load_class(path: str, base: type[T], error: type[LookupError], what: str) -> type[T]:
    """The `base` subclass at import path `path`; raises `error` naming `what` was asked for and why
    it cannot be had (not an import path, a module that does not import, not a `base` subclass)."""
    module_name, _, attr = path.partition(":")
    if not module_name or not attr:
        raise error(f"{what} {path!r}: an import path must look like `package.module:ClassName`")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise error(f"cannot import module {module_name!r} for {what} {path!r}: {exc}") from None
    cls = getattr(module, attr, None)
    if not (isinstance(cls, type) and issubclass(cls, base)):
        raise error(f"{what} {path!r}: expected a {base.__name__} subclass, got {cls!r}")
    return cls
