"""The import contract (docs/architecture.md, "The house"): every module of picdrive and
picdrive_hil in one layer, imports only downwards (those inside functions included), no cycle.

The checker (tests/support/import_contract.py) reads the source, so it is also run on small
synthetic trees: a deliberately added back-edge, a cycle and an unplaced module must fail."""
from pathlib import Path

import pytest

from support import import_contract as contract

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def tree():
    return contract.scan(contract.repo_packages(ROOT))


def test_the_tree_keeps_the_contract(tree, report_section):
    assert len(tree.modules) > 50            # the scan saw the packages, not an empty folder
    report_section("import contract", contract.report(tree))
    bad = contract.violations(tree)
    assert bad == [], "\n".join(bad)


def test_the_layers_say_what_the_issue_asks():
    allowed = {name: set(deps) for name, (_, deps) in contract.LAYERS.items()}
    # models <- analysis <- design <- papers, each strictly above the one before
    assert allowed["models"] == {"core"}
    assert allowed["analysis"] == {"models", "core"}
    assert allowed["design"] == {"analysis", "models", "core"}
    assert {"design", "analysis", "models"} <= allowed["papers"]
    # design never imports the firmware, the link or the twin
    assert not allowed["design"] & {"firmware", "link", "twin", "gate", "papers", "console"}
    # the firmware depends only on the law and the profile (core) and the protocol it renders into C
    assert allowed["firmware"] == {"link", "core"}
    # the console is built on the link (and the step figures of analysis); the firmware owns the
    # law -> parameter mapping the console's 'load' pushes; never the twin, the design or the gate
    assert allowed["console"] == {"firmware", "link", "analysis", "core"}
    # the twin depends on the firmware, the link and the profile only
    assert allowed["twin"] == {"firmware", "link", "core"}
    # nothing below the top imports a layer that imports it: the table itself is acyclic
    order = list(contract.LAYERS)
    for name, deps in allowed.items():
        assert all(order.index(d) < order.index(name) for d in deps), name


def _write(root: Path, files: dict[str, str]) -> list[Path]:
    for rel, text in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    return [root / "picdrive"]


BASE = {
    "picdrive/__init__.py": "",
    "picdrive/profile.py": "",
    "picdrive/models/__init__.py": "",
    "picdrive/models/plant.py": "from ..profile import x\n",
    "picdrive/design/__init__.py": "",
    "picdrive/design/method.py": "from ..models.plant import y\n",
    "picdrive/firmware/__init__.py": "",
    "picdrive/firmware/codegen.py": "from .. import profile\n",
}


def test_a_clean_synthetic_tree_passes(tmp_path):
    t = contract.scan(_write(tmp_path, BASE))
    assert contract.violations(t) == []
    assert t.imports["picdrive.design.method"] == {"picdrive.models.plant": 1}
    assert t.imports["picdrive.firmware.codegen"] == {"picdrive.profile": 1}


def test_a_back_edge_inside_a_function_fails(tmp_path):
    files = dict(BASE)
    files["picdrive/models/plant.py"] = ("from ..profile import x\n\n\ndef f():\n"
                                         "    from ..design.method import y   # the back-edge\n    return y\n")
    bad = contract.violations(contract.scan(_write(tmp_path, files)))
    assert any(b.startswith("picdrive.models.plant:5 (models) imports picdrive.design.method (design)") for b in bad), bad
    assert any("import cycle" in b for b in bad), bad      # models.plant <-> design.method


def test_design_importing_the_firmware_fails(tmp_path):
    files = dict(BASE)
    files["picdrive/design/method.py"] = "import picdrive.firmware.codegen as cg\n"
    bad = contract.violations(contract.scan(_write(tmp_path, files)))
    assert bad == ["picdrive.design.method:1 (design) imports picdrive.firmware.codegen (firmware): design may "
                   "import only analysis, core, design, models"]


def test_a_literal_import_module_counts(tmp_path):
    files = dict(BASE)
    files["picdrive/models/plant.py"] = 'import importlib\n\ndef f():\n    return importlib.import_module("picdrive.design.method")\n'
    bad = contract.violations(contract.scan(_write(tmp_path, files)))
    assert any("picdrive.models.plant:4 (models) imports picdrive.design.method" in b for b in bad), bad


def test_a_cycle_inside_a_layer_fails(tmp_path):
    files = dict(BASE)
    files["picdrive/design/a.py"] = "def f():\n    from . import b\n"
    files["picdrive/design/b.py"] = "from .a import f\n"
    bad = contract.violations(contract.scan(_write(tmp_path, files)))
    assert bad == ["import cycle: picdrive.design.a <-> picdrive.design.b"]


def test_a_module_outside_every_layer_fails(tmp_path):
    files = dict(BASE)
    files["picdrive/attic.py"] = ""
    bad = contract.violations(contract.scan(_write(tmp_path, files)))
    assert bad == ["picdrive.attic: in no layer (add it to LAYERS in tests/support/import_contract.py)"]


def test_the_report_lists_the_layers_bottom_to_top(tree):
    text = contract.report(tree)
    lines = [ln.split()[0] for ln in text.splitlines()[1:] if ln.startswith("  ") and not ln.startswith("   ")]
    assert lines == list(contract.LAYERS)
    assert "picdrive.design.verify" in text and "picdrive_hil.twin" in text

