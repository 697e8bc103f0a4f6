"""The package's layers: imports run one way, from cli down to geometry; the baseline never
imports the method it is compared with; modules and functions stay short."""
import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "surfelwarp"
TOOLS = Path(__file__).resolve().parents[1] / "data_tools"

# A unit may import only units of a lower rank (leaf utilities import nothing of the package).
RANK = {"errors": 0, "timing": 0, "geometry": 1, "io": 2, "render": 2, "preprocess": 2, "deform": 3,
        "tracking": 4, "methods": 5, "methods.surfelwarp": 5.5, "methods.dynamicfusion": 5.5, "config": 6,
        "run": 6, "data_tools": 7, "batch": 7.5, "report": 8, "cli": 9, "__main__": 10}


def unit(module: str) -> str:
    parts = module.split(".")[1:]
    if parts[:1] == ["methods"] and len(parts) > 1 and parts[1] in ("surfelwarp", "dynamicfusion"):
        return "methods." + parts[1]
    return parts[0]


def imports(root: Path, package: str):
    for path in root.rglob("*.py"):
        module = ".".join((package,) + path.relative_to(root).with_suffix("").parts).removesuffix(".__init__")
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("surfelwarp."):
                yield path, module, node.module


def test_units_import_only_lower_layers():
    wrong = []
    for path, module, target in list(imports(PACKAGE, "surfelwarp")) + list(imports(TOOLS, "surfelwarp.data_tools")):
        a, b = unit(module), unit(target)
        if a != b and not RANK[b] < RANK[a]:
            wrong.append(f"{path.relative_to(PACKAGE.parent)}: {module} imports {target}")
    assert not wrong, "\n".join(wrong)


def test_every_unit_has_a_rank():
    units = {unit("surfelwarp." + ".".join(p.relative_to(PACKAGE).with_suffix("").parts))
             for p in PACKAGE.rglob("*.py") if p.name != "__init__.py" or p.parent != PACKAGE}
    assert units <= set(RANK), units - set(RANK)


@pytest.mark.parametrize("root", [PACKAGE, TOOLS], ids=["surfelwarp", "data_tools"])
def test_modules_and_functions_stay_short(root):
    long = []
    for path in root.rglob("*.py"):
        text = path.read_text()
        if text.count("\n") > 400:
            long.append(f"{path.name}: {text.count(chr(10))} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno - node.lineno >= 80:
                long.append(f"{path.name}:{node.lineno} {node.name}: {node.end_lineno - node.lineno + 1} lines")
    assert not long, "\n".join(long)
