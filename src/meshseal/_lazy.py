"""Packages whose public names are imported on first use, so that importing the package (the command
line does, to build its parser) does not import torch, numba or trimesh.

`export_lazily(__name__, {name: ".submodule"})` at the end of a package's `__init__` makes `package.name`
import `package.submodule` and return its `name` the first time it is asked for (".submodule:other" returns
the submodule's `other` under the name `name`). Where a public function
has the name of its own submodule (`meshseal.render.interpolate`, `meshseal.data.build`), the package's
attribute stays the function, as an eager import in `__init__` would leave it: the import system's
recording of the submodule on the package is skipped (the submodule stays in `sys.modules`).
"""

from __future__ import annotations

import importlib
import sys
import types


def export_lazily(package: str, exports: dict[str, str]) -> None:
    """Give the package `package` the public names `exports` (name -> relative submodule, or
    "submodule:attribute"), each imported on first access."""
    module = sys.modules[package]

    class LazyPackage(types.ModuleType):
        def __getattr__(self, name: str):
            if name not in exports:
                raise AttributeError(f"module {package!r} has no attribute {name!r}")
            where, _, attribute = exports[name].partition(":")
            value = getattr(importlib.import_module(where, package), attribute or name)
            self.__dict__[name] = value
            return value

        def __setattr__(self, name: str, value) -> None:
            if (name in exports and isinstance(value, types.ModuleType)
                    and value.__name__ == f"{package}.{name}"):
                return  # a submodule shadowed by the public name of the same name
            super().__setattr__(name, value)

        def __dir__(self):
            return sorted(set(self.__dict__) | set(exports))

    module.__class__ = LazyPackage
