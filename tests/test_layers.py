"""The import graph runs one way: cli -> experiments / robust -> attacks / labelling -> preferences / victims -> envs / agents."""

import ast
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src" / "rat"

# a package may import the packages of its own layer's right and every layer below it, never one above
LAYERS = [
    {"cli"},
    {"experiments", "robust"},
    {"attacks", "labelling"},
    {"preferences", "victims"},
    {"eval"},
    {"envs", "agents"},
    {"loop", "runs", "checkpoint", "reports", "seeds", "configs", "device", "errors", "plots", "plugins", "pages"},
]


def layer(name: str) -> int:
    return next(i for i, group in enumerate(LAYERS) if name in group)


def imports_of(path: Path) -> set[str]:
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("rat."):
            found.add(node.module.split(".")[1])
        elif isinstance(node, ast.Import):
            found |= {a.name.split(".")[1] for a in node.names if a.name.startswith("rat.")}
    return found


def test_no_module_imports_a_layer_above_its_own():
    wrong = []
    for path in SRC.rglob("*.py"):
        parts = path.relative_to(SRC).with_suffix("").parts
        if parts[0] in ("__init__", "zoo"):
            continue
        own = layer(parts[0])
        for name in imports_of(path):
            if name in ("zoo",):
                continue
            if layer(name) < own:
                wrong.append(f"{'/'.join(parts)} imports rat.{name}")
    assert not wrong, wrong
