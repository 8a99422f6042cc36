"""Optional packages, installed by pip extras (`topseg[cell]`, `[train]`, `[oak]`, ...):
whether one is installed, and the one line that says which extra brings a missing one."""

import importlib


def needs_extra(what: str, module: str, extra: str) -> str:
    """The one line for a feature whose optional package is missing, with the pip command
    that installs it: `oak: depthai is not installed (pip install 'topseg[oak]')`."""
    return f"{what}: {module} is not installed (pip install 'topseg[{extra}]')"


def is_installed(module: str) -> bool:
    """Whether `module` imports (an optional package that an extra installs)."""
    try:
        importlib.import_module(module)
    except ImportError:
        return False
    return True


def import_failure(what: str, module: str, extra: str, exc: ImportError) -> str:
    """The one line for `module` failing to import: the extra to install when the package is
    not installed, else what went wrong loading it (a missing system library)."""
    missing = exc.name if isinstance(exc, ModuleNotFoundError) else None
    if missing and missing.partition(".")[0] == module.partition(".")[0]:
        return needs_extra(what, module, extra)
    return f"{what}: cannot import {module}: {exc}"
