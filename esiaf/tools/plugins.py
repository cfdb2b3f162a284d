"""Plug-in analysers: a user's component run beside the built-in ones (``esiaf run --with``).

A plug-in is a folder whose ``__main__.py`` runs a component (``raise SystemExit(main(MyAnalyser))``),
a module runnable with ``python -m``, or the name of an installed distribution's entry point in
the ``esiaf.components`` group (``[project.entry-points."esiaf.components"] rate = "my_rate"``,
the value a module runnable with ``python -m``). Nothing of ESIAF's own files changes.
"""
from __future__ import annotations

import importlib.util
import re
from dataclasses import dataclass
from importlib.metadata import entry_points
from pathlib import Path

from esiaf.tools.launcher import LaunchError

ENTRY_POINT_GROUP = "esiaf.components"


@dataclass(frozen=True)
class Plugin:
    name: str  # shown in logs and messages: the folder's or module's name
    target: list[str]  # what follows ``python``: a folder, or -m and a module


def resolve(spec: str) -> Plugin:
    """A folder (with __main__.py), an entry point name, or a module; LaunchError if none."""
    path = Path(spec).expanduser()
    if path.is_dir():
        if not (path / "__main__.py").is_file():
            raise LaunchError(f"--with {spec}: the folder has no __main__.py (it must run the component, "
                              f"e.g. raise SystemExit(main(MyAnalyser)))")
        return Plugin(_safe_name(path.resolve().name), [str(path.resolve())])
    found = [ep for ep in entry_points(group=ENTRY_POINT_GROUP) if ep.name == spec]
    if found:
        return Plugin(_safe_name(spec), ["-m", found[0].value])
    if re.fullmatch(r"[A-Za-z_][\w.]*", spec) and importlib.util.find_spec(spec.split(".")[0]) is not None:
        return Plugin(_safe_name(spec.rsplit(".", 1)[-1]), ["-m", spec])
    raise LaunchError(f"--with {spec}: not a folder, nor an installed component (entry point group "
                      f"{ENTRY_POINT_GROUP}), nor a module")


def _safe_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name) or "plugin"
