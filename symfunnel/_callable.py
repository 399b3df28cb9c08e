"""Three command names are also module names (`symfunnel.simulate`, `.codegen`, `.report`): Python binds a package's
submodule to the package attribute of the same name whenever it is imported, which would shadow the API function.
Those modules are made callable instead, so `symfunnel.simulate(...)` is the API function whichever way the name was
reached, and `symfunnel.simulate.simulate` etc. stay what they were.
"""

from __future__ import annotations

import importlib
import sys
import types


def make_callable(module_name: str, api_name: str) -> None:
    """Calling module `module_name` calls `symfunnel.api.<api_name>` (imported on first call)."""
    def __call__(self, *args, **kwargs):
        return getattr(importlib.import_module("symfunnel.api"), api_name)(*args, **kwargs)

    cls = type("CommandModule", (types.ModuleType,), {"__call__": __call__,
                                                       "__doc__": f"module and API function symfunnel.{api_name}"})
    sys.modules[module_name].__class__ = cls
