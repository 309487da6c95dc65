"""The generated firmware's inline PIC18 assembly names what it addresses.

Every configuration the generator emits (both speed sources, halls on INT and on IC, 1 to 8
rules, derivative filter and reference feedforward each on and off, link capture and EEPROM
left out, and every bundled design) is rendered; in each source's ``__asm ... __endasm``
blocks no register is written by its address (``0xFF3`` for PRODL: the names come from
p18f4431.inc) and no field of a struct is reached by a literal offset (``_core_s + 24``: the
offsets are named, ``_core_s + CORE_S_SPEED``, and each name is checked against ``offsetof``
at compile time).  A number after a named offset is a byte within that field
(``_core_s + CORE_S_PDC + 1``); a number after an array or a scalar is an element or a byte
of it, which is allowed.  Every function holding assembly states its contract in the comment
above it (inputs, outputs, registers clobbered, overflow behaviour).
"""
from __future__ import annotations

import json
import re

import pytest

from picdrive.control_law import Rule, ScheduledLaw
from picdrive.firmware import codegen, p18f4431
from picdrive.paths import repo_root
from picdrive.profile import load_profile
from picdrive.result import DesignResult, save_design

EXAMPLES = repo_root() / "examples"
RPM = 3.141592653589793 / 30
MAX_RULES = 8                       # protocol.build_table's limit

_ASM = re.compile(r"__asm\b(.*?)__endasm", re.S)
_BRACE_OBJ = re.compile(r"\b(struct|union)\b(?:\s+(\w+))?\s*\{")
_SFR_LO, _SFR_HI = 0xF60, 0xFFF     # the 18F4431's SFRs (access bank's upper part)


def _structs(src: str) -> set[str]:
    """Names of the struct objects ``src`` defines (``struct {...} S;``, ``core_state_t core_s;``)."""
    objs, types, tags = set(), set(), set()
    for m in _BRACE_OBJ.finditer(src):
        depth, i = 0, m.end() - 1
        while True:
            depth += {"{": 1, "}": -1}.get(src[i], 0)
            if depth == 0:
                break
            i += 1
        before = src[max(0, m.start() - 20):m.start()]
        after = re.match(r"\s*(\w+)\s*;", src[i + 1:])
        if m[1] == "struct" and after:
            (types if "typedef" in before else objs).add(after[1])
            if m[2]:
                tags.add(m[2])
    for t in types:
        objs |= set(re.findall(rf"\b{t}\s+(\w+)\s*;", src))
    for t in tags:
        objs |= set(re.findall(rf"\bstruct\s+{t}\s+(\w+)\s*;", src))
    return objs


def asm_findings(files: dict[str, str]) -> dict[str, list[str]]:
    """{"sfr": [...], "offset": [...]}: raw SFR addresses and literal struct offsets in the
    assembly of the rendered C sources (file: line)."""
    srcs = {n: t for n, t in files.items() if n.endswith((".c", ".h"))}
    objs = set().union(*(_structs(t) for t in srcs.values()))
    obj_off = re.compile(r"\b_(" + "|".join(sorted(map(re.escape, objs))) + r")\s*\+\s*(?:0[xX])?\d")
    found = {"sfr": [], "offset": []}
    for name, text in sorted(srcs.items()):
        for block in _ASM.findall(text):
            for line in block.splitlines():
                code = line.split(";")[0]
                for tok in re.findall(r"\b(?:0[xX][0-9A-Fa-f]+|\d+)\b", code):
                    if _SFR_LO <= int(tok, 0) <= _SFR_HI:
                        found["sfr"].append(f"{name}: {line.strip()}")
                if objs and obj_off.search(code):
                    found["offset"].append(f"{name}: {line.strip()}")
    return found


def _law(nr: int, dfilt: bool, ff: bool) -> ScheduledLaw:
    rules = tuple(Rule(0.2 - 0.01 * j, 5.0 - 0.3 * j, 0.0005 if dfilt else 0.0, 10.0 - j) for j in range(nr))
    return ScheduledLaw(rules=rules, premise_rad_s=(0.0, 2600 * RPM), sample_time_s=1e-3, u_min_v=-44.16,
                        u_max_v=44.16, derivative_filter_hz=200.0 if dfilt else None,
                        reference_ff_v_s_per_rad=0.1 if ff else 0.0)


def _configurations():
    """(id, profile name, design maker, generate options): everything the generator emits."""
    for d in sorted(EXAMPLES.glob("*.design.json")):
        yield d.stem, json.loads(d.read_text())["profile"]["name"], (lambda tmp, d=d: d), {}
    halls = EXAMPLES / "duy2008_halls.fuzzy-hinf.design.json"
    yield "halls-on-ic", "duy2008_halls", (lambda tmp: halls), {"hall_input": "ic"}
    yield "no-capture-no-eeprom", "duy2008", (lambda tmp: EXAMPLES / "duy2008.fuzzy-hinf.design.json"), \
        {"link_capture": False, "link_eeprom": False}
    for pn in ("duy2008", "duy2008_halls"):            # the encoder's and the halls' speed
        for nr in range(1, MAX_RULES + 1):
            for dfilt in (False, True):
                for ff in (False, True):
                    name = f"{pn}-r{nr}{'-dfilt' if dfilt else ''}{'-ff' if ff else ''}"

                    def make(tmp, pn=pn, nr=nr, dfilt=dfilt, ff=ff, name=name):
                        prof = load_profile(pn)
                        return save_design(DesignResult(method="zn", status="verified", profile_name=prof.name,
                                                        profile_sha256=prof.sha256, law=_law(nr, dfilt, ff),
                                                        variant="test-fixture"), tmp / f"{name}.design.json")
                    yield name, pn, make, {}


def uncontracted(files: dict[str, str]) -> list[str]:
    """Functions holding assembly whose comment above (the 12 lines before the definition) has no
    "Contract" (inputs, outputs, registers clobbered, overflow behaviour)."""
    out = []
    for name, text in sorted(files.items()):
        if not name.endswith(".c"):
            continue
        lines = text.splitlines()
        for i, line in enumerate(lines):
            if line.strip() != "__asm":
                continue
            j = i
            while j > 0 and lines[j] != "{":          # the function's opening brace
                j -= 1
            if not any("Contract" in ln for ln in lines[max(0, j - 14):j]):
                out.append(f"{name}: {lines[j - 1].strip()}")
    return sorted(set(out))


def test_the_checker_finds_raw_addresses_and_literal_offsets():
    files = {"a.c": "typedef struct { int16_t a; int16_t b; } t_t;\nt_t core_s;\nstatic struct w { uint8_t x; } S;\n"
                    "uint8_t buf[4];\nvoid f(void) __naked\n{\n    __asm\n    MOVWF   0xFF3, A\n"
                    "    MOVFF   _core_s + 2, _S + CORE_X\n    MOVF    (_S + 0), W, B\n    MOVF    _buf + 3, W, A\n"
                    "    MOVFF   _core_s + CORE_S_B + 1, _PRODL\n    MOVLW   0xF0\n    __endasm;\n}\n"}
    got = asm_findings(files)
    assert got["sfr"] == ["a.c: MOVWF   0xFF3, A"]
    assert got["offset"] == ["a.c: MOVFF   _core_s + 2, _S + CORE_X", "a.c: MOVF    (_S + 0), W, B"]


def test_no_raw_sfr_address_or_literal_struct_offset_in_any_configuration(tmp_path):
    seen, blocks = set(), 0
    bad = {}
    for name, pn, make, opts in _configurations():
        fw = codegen.generate(load_profile(pn), make(tmp_path), **opts)
        blocks += sum(len(_ASM.findall(t)) for n, t in fw.files.items() if n.endswith(".c"))
        seen.add((fw.plan.speed_source, fw.pinmap.hall_input, fw.plan.n_rules, bool(fw.plan.dfilt_a),
                  bool(fw.plan.kff)))
        got = asm_findings(fw.files)
        got["no contract"] = uncontracted(fw.files)
        if any(got.values()):
            bad[name] = {k: v[:5] for k, v in got.items() if v}
    assert not bad, json.dumps(bad, indent=1)
    # the configurations are what they say: both sources, both hall inputs, every rule count,
    # the filter and the feedforward each on and off
    assert {s[0] for s in seen} == {"encoder", "hall"} and {s[1] for s in seen} == {"int", "ic"}
    assert {s[2] for s in seen} == set(range(1, MAX_RULES + 1))
    assert {(s[3], s[4]) for s in seen} == {(False, False), (False, True), (True, False), (True, True)}
    assert blocks > 1000


@pytest.mark.parametrize("name", ["drive.c.j2", "drive_core.c.j2", "link_fw.c.j2", "main_sdcc.c.j2"])
def test_the_templates_hold_no_register_address(name):
    """The templates themselves, comments included: a register is named, never numbered."""
    text = (repo_root() / "firmware_templates" / name).read_text()
    assert not re.findall(r"\b0[xX][Ff][0-9A-Fa-f]{2}\b", text)
    assert p18f4431.registers()["PRODL"] == 0xFF3          # the names the assembly uses are the .inc's


def test_a_wrong_offset_name_does_not_compile(tmp_path, monkeypatch):
    """The offsets are checked against the structs at compile time: CORE_S_SPEED one byte off
    (as if the description and the struct disagreed) stops SDCC at the layout check."""
    from picdrive.firmware import core_layout, target
    real = core_layout.Struct.c_offsets

    def off_by_one(self, n_rules):
        text = real(self, n_rules)
        return text.replace(f"#define CORE_S_SPEED {self.offsets(n_rules)['speed']}",
                            f"#define CORE_S_SPEED {self.offsets(n_rules)['speed'] + 1}") \
            if self is core_layout.CORE_STATE else text
    monkeypatch.setattr(core_layout.Struct, "c_offsets", off_by_one)
    fw = codegen.generate(load_profile("duy2008"), EXAMPLES / "duy2008.fuzzy-hinf.design.json")
    assert "#define CORE_S_SPEED 25" in fw.files["drive_core.h"]
    folder = codegen.write_firmware(fw, tmp_path / "fw", check=False)
    with pytest.raises(target.TargetError, match="core_state_layout"):
        target.build_hex(folder, tmp_path / "hex", name="wrong")
