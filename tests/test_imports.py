"""The import graph of esiaf, esiaf_services and bench has no cycles, and the orchestrator's packages
keep their layers (the import-linter contracts in pyproject.toml): CI checks it here.

The graph is grimp's (what import-linter uses), imports under TYPE_CHECKING and inside functions
included. The last tests show that both checks do fail on a cycle, so a pass means something.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import grimp
import pytest

from esiaf.tools.testing import REPO

BIN = Path(sys.executable).parent  # the virtual environment's bin (not resolved: that would leave it)
PACKAGES = ("esiaf", "esiaf_services", "bench")


def import_graph(*packages: str, root: Path = REPO) -> grimp.ImportGraph:
    sys.path.insert(0, str(root))
    try:
        return grimp.build_graph(*packages, exclude_type_checking_imports=False, cache_dir=None)
    finally:
        sys.path.remove(str(root))


def cycles(graph: grimp.ImportGraph) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's, without recursion):
    each is a set of modules that import each other, directly or not."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    for start in sorted(graph.modules):
        if start in index:
            continue
        work = [(start, iter(sorted(graph.find_modules_directly_imported_by(start))))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            module, imported = work[-1]
            for other in imported:
                if other not in index:
                    index[other] = low[other] = len(index)
                    stack.append(other)
                    on_stack.add(other)
                    work.append((other, iter(sorted(graph.find_modules_directly_imported_by(other)))))
                    break
                if other in on_stack:
                    low[module] = min(low[module], index[other])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[module])
                if low[module] == index[module]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == module:
                            break
                    if len(component) > 1:
                        found.append(sorted(component))
    return found


def describe(graph: grimp.ImportGraph, cycle: list[str]) -> str:
    """One cycle as the chain from its first module back to itself."""
    first = cycle[0]
    back = next(m for m in cycle if graph.direct_import_exists(importer=m, imported=first))
    chain = graph.find_shortest_chain(importer=first, imported=back) or (first, back)
    return " -> ".join([*chain, first])


def lint_imports(*args: str, cwd: Path = REPO) -> subprocess.CompletedProcess:
    tool = BIN / "lint-imports"
    if not tool.exists():
        pytest.fail(f"{tool} is missing: the test extra installs it (./setup.sh)")
    return subprocess.run([str(tool), "--no-cache", *args], cwd=cwd, capture_output=True, text=True, timeout=600,
                          env={**os.environ, "PYTHONPATH": str(cwd)})


def test_no_module_imports_itself_through_others():
    graph = import_graph(*PACKAGES)
    found = cycles(graph)
    assert not found, "import cycles:\n" + "\n".join(describe(graph, cycle) for cycle in found)


def test_import_contracts_are_kept():
    done = lint_imports()  # the contracts in pyproject.toml
    assert done.returncode == 0, f"import-linter found broken contracts:\n{done.stdout}{done.stderr}"


@pytest.fixture
def cyclic_package(tmp_path: Path) -> Path:
    """A package whose modules a and b import each other (b only for the type checker), and whose
    pyproject.toml asks for no cycles."""
    package = tmp_path / "loop"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "a.py").write_text("from loop.b import B\n\n\nclass A(B):\n    pass\n")
    (package / "b.py").write_text("from typing import TYPE_CHECKING\n\nif TYPE_CHECKING:\n"
                                  "    from loop.a import A\n\n\n"
                                  "class B:\n    def child(self) -> 'A':\n        raise NotImplementedError\n")
    (tmp_path / "pyproject.toml").write_text(
        '[tool.importlinter]\nroot_packages = ["loop"]\nexclude_type_checking_imports = false\n\n'
        '[[tool.importlinter.contracts]]\nname = "no cycles"\ntype = "acyclic_siblings"\nancestors = ["loop"]\n')
    return tmp_path


def test_both_checks_fail_on_a_cycle(cyclic_package):
    graph = import_graph("loop", root=cyclic_package)
    assert cycles(graph) == [["loop.a", "loop.b"]]
    assert describe(graph, ["loop.a", "loop.b"]) == "loop.a -> loop.b -> loop.a"
    done = lint_imports(cwd=cyclic_package)
    assert done.returncode == 1 and "BROKEN" in done.stdout, done.stdout + done.stderr
