"""The README's layer drawing holds: no module imports (at run time) from a layer above its own."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "torchsfm"

# the README's drawing, top to bottom; one row may import within itself
LAYERS = [
    {"cli", "actions", "__main__"},
    {"io"},
    {"sfm"},
    {"reconstruction", "evaluation", "visualization", "testing"},
    {"moving", "calibration"},
    {"estimators"},
    {"robust", "optim"},
    {"features", "matching"},
    {"geometry", "camera", "images"},
    {"config", "errors", "validation", "numerics", "pipeline", "threads", "inference", "io.atomic", "io.exif"},
]


def _layer(module: str) -> int:
    """Row of a module path like ``sfm.stages`` (0 = top)."""
    parts = module.split(".")
    for depth in (2, 1):
        name = ".".join(parts[:depth])
        for row, units in enumerate(LAYERS):
            if name in units:
                return row
    raise AssertionError(f"{module} is in no layer of the drawing")


def _runtime_imports(tree: ast.Module) -> list[str]:
    """torchsfm modules imported outside ``if TYPE_CHECKING:`` blocks."""
    typing_only = {id(node) for block in ast.walk(tree) if isinstance(block, ast.If) and "TYPE_CHECKING" in ast.dump(block.test)
                   for node in ast.walk(block)}
    return [node.module.removeprefix("torchsfm.") for node in ast.walk(tree)
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("torchsfm.") and id(node) not in typing_only]


def test_no_module_imports_from_a_layer_above_it():
    upward = []
    for path in PACKAGE.rglob("*.py"):
        module = ".".join(path.relative_to(PACKAGE).with_suffix("").parts)
        if module == "__init__":
            continue
        own = _layer(module)
        upward += [f"{module} -> {target}" for target in _runtime_imports(ast.parse(path.read_text())) if _layer(target) < own]
    assert upward == []
