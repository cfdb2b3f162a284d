"""Which services there are, and their settings models, known without starting or hosting any: the
built-in ones (``esiaf_services/*/`` with a ``__main__.py``) and the installed plug-ins (entry point
group ``esiaf.components``). Used by ``esiaf run`` to check settings before anything starts, by the
services to tell a misspelt variable, and by the configuration page's generator.
"""
from __future__ import annotations

import ast
import importlib
import importlib.util
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

from esiaf.settings import ComponentSettings


def known_services() -> set[str]:
    """The built-in services (esiaf_services/*/ with a __main__.py) and the installed plug-ins (entry
    point group esiaf.components)."""
    spec = importlib.util.find_spec("esiaf_services")
    folders = [Path(p) for p in (spec.submodule_search_locations or [])] if spec else []
    built_in = {d.name for folder in folders for d in folder.iterdir() if (d / "__main__.py").is_file()}
    return built_in | {ep.name for ep in entry_points(group="esiaf.components")}


def entry_class(main_file: Path) -> Any:
    """The class a service's ``__main__.py`` passes to ``main(...)``, imported."""
    tree = ast.parse(main_file.read_text())
    imported = {alias.asname or alias.name: node.module for node in ast.walk(tree)
                if isinstance(node, ast.ImportFrom) and node.module for alias in node.names}
    for node in ast.walk(tree):
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "main"
                and node.args and isinstance(node.args[0], ast.Name) and node.args[0].id in imported):
            name = node.args[0].id
            return getattr(importlib.import_module(imported[name]), name)
    raise LookupError(f"{main_file}: no main(SomeComponent) call to find the service's settings by")


def service_settings(service: str) -> type[ComponentSettings] | None:
    """The settings model of a built-in service (of the class its ``__main__.py`` runs) or of an
    installed plug-in; None when there is no such service or it cannot be loaded here (it then says
    why itself as it starts)."""
    spec = importlib.util.find_spec("esiaf_services")
    for folder in spec.submodule_search_locations or [] if spec else []:
        main_file = Path(folder) / service / "__main__.py"
        if main_file.is_file():
            return entry_class(main_file).Settings
    for point in entry_points(group="esiaf.components"):
        if point.name == service:
            try:
                return point.load().Settings
            except Exception:  # a broken plug-in: its own start says what is wrong
                return None
    return None
