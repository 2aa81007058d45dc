"""ftrain: distributed, fault-tolerant PPO training on CPU."""

import importlib.util
import os
import sys
import types

# rsl_rl imports GitPython, which refuses to import where no git binary exists unless told to stay quiet.
os.environ.setdefault("GIT_PYTHON_REFRESH", "quiet")


class _RunsOnFirstUse(types.ModuleType):
    """A module whose code runs the first time an attribute it lacks is asked for (its spec's ``__file__``,
    ``__path__`` and the like it has from the start: ``inspect.getmodule``, which torch calls at import, looks at
    every module's ``__file__``, and would load a ``importlib.util.LazyLoader`` module)."""

    def __getattr__(self, attr: str) -> object:
        self.__class__ = types.ModuleType  # a plain module from here on, whatever its code does
        self.__spec__.loader.exec_module(self)
        return getattr(self, attr)


def _import_on_first_use(name: str) -> None:
    """rsl-rl imports wandb at import time, for a writer ftrain does not use. That cost every worker about 0.9 s, a
    fifth of its start-up, and wandb creates two temporary directories on import that it removes only at a clean
    exit: every worker killed, or forked and ended with ``os._exit``, left them in /tmp for good (thousands after a
    day of restarts). A run with W&B on gets the whole module the moment its tracker uses it."""
    if name in sys.modules or (spec := importlib.util.find_spec(name)) is None or spec.loader is None:
        return
    module = importlib.util.module_from_spec(spec)
    module.__class__ = _RunsOnFirstUse
    sys.modules[name] = module


_import_on_first_use("wandb")
