"""ftrain: distributed, fault-tolerant PPO training on CPU."""

import importlib.util
import os
import sys
import types

# rsl_rl imports GitPython, which refuses to import where no git binary exists unless told to stay quiet.
os.environ.setdefault("GIT_PYTHON_REFRESH", "quiet")


class _RunsOnFirstUse(types.ModuleType):
    """A module whose code runs the first time an attribute it lacks is asked for. It has its ``__file__`` from the
    start (``inspect.getmodule``, which torch calls at import, looks at every module's ``__file__``, and would load a
    ``importlib.util.LazyLoader`` module), but not its ``__path__``: importing a submodule asks for it, and so runs
    the package first, as a plain import does. Code that fails leaves no half-run module behind."""

    def __getattr__(self, attr: str) -> object:
        self.__class__ = types.ModuleType  # a plain module from here on, whatever its code does
        self.__path__ = self.__spec__.submodule_search_locations
        try:
            self.__spec__.loader.exec_module(self)
        except BaseException:
            sys.modules.pop(self.__name__, None)
            raise
        return getattr(self, attr)


def _import_on_first_use(name: str) -> None:
    """rsl-rl imports wandb at import time, for a writer ftrain does not use. That cost every worker about 0.9 s, a
    fifth of its start-up, and wandb creates two temporary directories on import that it removes only at a clean
    exit: every worker killed, or forked and ended with ``os._exit``, left them in /tmp for good (thousands after a
    day of restarts). A run with W&B on gets the whole module the moment its tracker uses it."""
    if name in sys.modules or (spec := importlib.util.find_spec(name)) is None or spec.loader is None:
        return
    module = importlib.util.module_from_spec(spec)
    del module.__path__  # see _RunsOnFirstUse
    module.__class__ = _RunsOnFirstUse
    sys.modules[name] = module


_import_on_first_use("wandb")
