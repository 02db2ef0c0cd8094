"""The equation table of docs/ARCHITECTURE.md names code that exists.

Each row's last cell reads ``\\`smln.module\\` · \\`name\\`, \\`name\\`; \\`smln.other\\` · ...``: every name must be an
attribute of that module, a dotted ``Class.attribute`` of it, or a method of one of its classes (a bare method name
such as ``build``). A renamed or moved function then fails here instead of leaving the table stale.
"""

from __future__ import annotations

import importlib
import inspect
import re
from pathlib import Path

import pytest

ARCHITECTURE = Path(__file__).resolve().parents[1] / "docs" / "ARCHITECTURE.md"
MODULE_MARK = re.compile(r"(`smln(?:\.\w+)+` · )")
NAME = re.compile(r"`(\w+(?:\.\w+)?)`")


def equation_table_references() -> list[tuple[str, str]]:
    """(module, name) pairs from the last cell of every table row with a ``module · name`` reference."""
    refs: list[tuple[str, str]] = []
    for line in ARCHITECTURE.read_text().splitlines():
        if not line.startswith("| ") or "` · `" not in line:
            continue
        last_cell = line.rstrip(" |").split("|")[-1]
        parts = MODULE_MARK.split(last_cell)
        for mark, rest in zip(parts[1::2], parts[2::2], strict=True):
            module = mark.split("`")[1]
            names_part = rest.split("(")[0]  # parenthesised remarks name things of other modules
            refs.extend((module, name) for name in NAME.findall(names_part))
    return refs


def resolves(module_name: str, name: str) -> bool:
    """Whether ``name`` is a (dotted) attribute of the module or a method of one of the module's classes."""
    module = importlib.import_module(module_name)
    obj: object = module
    try:
        for part in name.split("."):
            obj = getattr(obj, part)
        return True
    except AttributeError:
        pass
    if "." in name:
        return False
    classes = [c for _, c in inspect.getmembers(module, inspect.isclass) if c.__module__ == module.__name__]
    return any(hasattr(c, name) for c in classes)


def test_the_table_has_references() -> None:
    refs = equation_table_references()
    assert len(refs) >= 30, "the equation table of docs/ARCHITECTURE.md lost its module · function column"
    assert {m for m, _ in refs} >= {"smln.graph.multilayer", "smln.model.repulsion", "smln.losses.repulsion"}


@pytest.mark.parametrize(("module", "name"), equation_table_references())
def test_every_referenced_name_exists(module: str, name: str) -> None:
    assert resolves(module, name), f"docs/ARCHITECTURE.md names `{module}` · `{name}`, which does not exist"


def test_a_missing_name_is_caught() -> None:
    assert resolves("smln.model.repulsion", "init_as_projection")
    assert not resolves("smln.model.repulsion", "no_such_function_anywhere")
    assert not resolves("smln.graph.multilayer", "GraphTopology.no_such_method")
