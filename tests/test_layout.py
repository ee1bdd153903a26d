"""The package's shape: import layers, no cycles, public seams, sizes, and the module
map of ``docs/index.md`` against the package."""

from __future__ import annotations

import ast
import dataclasses
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import REPO_ROOT

SRC = REPO_ROOT / "src" / "subslope"

#: Rooms of the package by layer: a module imports only from its own room or from
#: rooms of a lower layer (inside functions too).
LAYERS = {
    "_version": 0,
    "config": 0,
    "ragged": 0,
    "devices": 0,
    "logs": 0,
    "digests": 0,
    "physics": 1,
    "stats": 1,
    "render": 2,
    "io": 2,
    "simulation": 3,
    "nre": 3,
    "validation": 4,
    "figures": 5,
    "plan": 6,
    "stages": 7,
    "campaigns": 8,
    "cli": 9,
}
MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 80


def _modules() -> dict[str, Path]:
    out = {}
    for path in sorted(SRC.rglob("*.py")):
        parts = path.relative_to(SRC.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def _room(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def _imports(path: Path, module: str) -> set[str]:
    """Every subslope module ``path`` imports, at any depth of the file."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name.split(".")[0] == "subslope"}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parent + ([base] if base else []))
            if base.split(".")[0] != "subslope":
                continue
            for alias in node.names:
                found.add(f"{base}.{alias.name}" if f"{base}.{alias.name}" in MODULES else base)
    return {m for m in found if m in MODULES and m != module}


MODULES = _modules()
GRAPH = {name: _imports(path, name) for name, path in MODULES.items()}


def test_every_room_has_a_layer():
    rooms = {_room(m) for m in MODULES if m != "subslope"}
    assert rooms <= set(LAYERS), sorted(rooms - set(LAYERS))


def test_imports_follow_the_layers():
    bad = []
    for module, targets in GRAPH.items():
        if module == "subslope":
            continue  # the package map re-exports lazily
        for target in targets:
            if target == "subslope":
                continue
            a, b = _room(module), _room(target)
            if a != b and LAYERS[b] >= LAYERS[a]:
                bad.append(f"{module} (layer {LAYERS[a]}) imports {target} (layer {LAYERS[b]})")
    assert not bad, "\n".join(bad)


def test_no_import_cycles():
    state: dict[str, int] = {}
    cycles = []

    def visit(node, stack):
        state[node] = 1
        for nxt in sorted(GRAPH[node]):
            if state.get(nxt) == 1:
                cycles.append(" -> ".join(stack[stack.index(nxt) :] + [nxt]))
            elif nxt not in state:
                visit(nxt, stack + [nxt])
        state[node] = 2

    for name in sorted(GRAPH):
        if name not in state:
            visit(name, [name])
    assert not cycles, "\n".join(cycles)


def test_module_and_function_sizes():
    long_modules = [
        f"{p.relative_to(REPO_ROOT)}: {n} lines"
        for p in MODULES.values()
        if (n := len(p.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES
    ]
    long_functions = []
    for path in MODULES.values():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    long_functions.append(
                        f"{path.relative_to(REPO_ROOT)}:{node.lineno} {node.name}: {n} lines"
                    )
    assert not long_modules and not long_functions, "\n".join(long_modules + long_functions)


def _private_uses(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    aliases, out = {}, []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("subslope"):
            for a in node.names:
                if a.name.startswith("_") and not a.name.startswith("__"):
                    out.append(
                        f"{path.relative_to(REPO_ROOT)}:{node.lineno} imports "
                        f"{node.module}.{a.name}"
                    )
                aliases[a.asname or a.name] = f"{node.module}.{a.name}"
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("subslope"):
                    aliases[(a.asname or a.name).split(".")[0]] = a.name
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Attribute)
            and node.attr.startswith("_")
            and not node.attr.startswith("__")
            and isinstance(node.value, ast.Name)
            and node.value.id in aliases
        ):
            out.append(
                f"{path.relative_to(REPO_ROOT)}:{node.lineno} uses "
                f"{aliases[node.value.id]}.{node.attr}"
            )
    return out


def test_tests_benchmarks_and_studies_use_public_names_only():
    files = [
        p for d in ("tests", "benchmarks", "studies") for p in sorted((REPO_ROOT / d).rglob("*.py"))
    ]
    uses = [line for path in files for line in _private_uses(path)]
    assert not uses, "\n".join(uses)


def test_tests_import_nothing_from_benchmarks_or_studies():
    """Tests exercise the package: a helper that a test and a benchmark share lives in
    ``subslope`` (e.g. :mod:`subslope.validation.scenes`), not in a script folder."""
    scripts = {p.stem for d in ("benchmarks", "studies") for p in (REPO_ROOT / d).glob("*.py")}
    bad = []
    for path in sorted((REPO_ROOT / "tests").rglob("*.py")):
        text = path.read_text(encoding="utf-8")
        if re.search(r"sys\.path\.(insert|append)\(.*(benchmarks|studies)", text):
            bad.append(f"{path.name}: puts benchmarks/ or studies/ on sys.path")
        for node in ast.walk(ast.parse(text)):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and not node.level:
                names = [node.module or ""]
            bad += [f"{path.name}:{node.lineno} imports {n}" for n in names if n in scripts]
    assert not bad, "\n".join(bad)


def test_docs_module_map_matches_the_package():
    text = (REPO_ROOT / "docs" / "index.md").read_text(encoding="utf-8")
    documented = set(re.findall(r"`(subslope(?:\.[a-z_0-9]+)*)`", text))
    modules = {m for m in MODULES if not m.split(".")[-1].startswith("_")}
    assert modules - documented == set(), (
        f"modules missing from docs/index.md: {sorted(modules - documented)}"
    )
    stale = {m for m in documented if m not in MODULES and not _is_attribute(m)}
    assert not stale, f"docs/index.md names modules that do not exist: {sorted(stale)}"


def _is_attribute(dotted: str) -> bool:
    module, _, attr = dotted.rpartition(".")
    return (
        module in MODULES
        and re.search(
            rf"^(def|class) {attr}\b|^{attr} = ", MODULES[module].read_text(encoding="utf-8"), re.M
        )
        is not None
    )


def test_every_render_setting_is_a_config_key():
    from subslope.config import load_schema
    from subslope.render.settings import INSTRUMENT_FIELDS, NOT_RENDER_KEYS, RenderSettings

    schema = load_schema()["properties"]
    render_keys = set(schema["simulation"]["properties"]["render"]["properties"]) - set(
        NOT_RENDER_KEYS
    )
    fields = {f.name for f in dataclasses.fields(RenderSettings)}
    assert fields - set(INSTRUMENT_FIELDS) == render_keys
    assert set(INSTRUMENT_FIELDS) <= set(schema["instrument"]["properties"])


def test_render_defaults_are_the_schema_defaults():
    from subslope.config import schema_defaults
    from subslope.render.settings import NOT_RENDER_KEYS, RenderSettings

    default = RenderSettings()
    for key, value in schema_defaults("simulation.render").items():
        if key in NOT_RENDER_KEYS or key in ("dtype", "device"):
            continue
        assert getattr(default, key) == value, key
    assert str(default.dtype) == f"torch.{schema_defaults('simulation.render')['dtype']}"


def test_planning_imports_no_heavy_library():
    """What the workflow imports to plan a run (``snakemake -n``) needs no torch, h5py,
    matplotlib, astropy or colossus."""
    code = (
        "import sys, subslope.config, subslope.plan, subslope.stages.train, "
        "subslope.io.resources, "
        "subslope.simulation.scenes, subslope\n"
        "heavy = sorted({m.split('.')[0] for m in sys.modules} & "
        "{'torch', 'h5py', 'matplotlib', 'astropy', 'colossus', 'pooch'})\n"
        "print(','.join(heavy))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "", out.stdout


def _stage_flags() -> list[str]:
    from subslope.config import schema_defaults

    return sorted(schema_defaults("stages"))


@pytest.mark.parametrize("flag", _stage_flags())
def test_stage_flag_rule_file_and_module_share_a_name(flag):
    from subslope.config import STAGE_NEEDS

    assert flag in STAGE_NEEDS
    assert (REPO_ROOT / "workflow" / "rules" / f"{flag}.smk").is_file()
    module = SRC / "stages" / flag
    assert module.with_suffix(".py").is_file() or (module / "__init__.py").is_file()


def test_subhalo_profiles_of_schema_scenes_and_registry_agree():
    import yaml

    from subslope.physics.pairs.registry import PAIR_PROFILES
    from subslope.simulation.scenes import LOS_PROFILES, SUBHALO_PROFILES

    text = (SRC / "schemas" / "config.schema.yaml").read_text(encoding="utf-8")
    enums = [
        node
        for node in _walk(yaml.safe_load(text))
        if isinstance(node, dict)
        and "enum" in node
        and set(node["enum"]) & {"epl", "nfw", "tnfw"}
        and "epl" in node["enum"]
    ]
    assert enums, "the schema lists no subhalo profile enum"
    assert set(SUBHALO_PROFILES) == set(PAIR_PROFILES)
    assert set(LOS_PROFILES) <= set(PAIR_PROFILES)
    assert {frozenset(e["enum"]) for e in enums} <= {
        frozenset(SUBHALO_PROFILES),
        frozenset(LOS_PROFILES),
    }


def _walk(node):
    yield node
    if isinstance(node, dict):
        for v in node.values():
            yield from _walk(v)
    elif isinstance(node, list):
        for v in node:
            yield from _walk(v)
