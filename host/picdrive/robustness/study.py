"""``picdrive robustness``: the tolerance study of a design's firmware on drives off the line.

    picdrive robustness --profile P --design D [--hex FILE] --samples N -o DIR
                        [--scheduler tcp://HOST:PORT] [--workers N] [--seed S] [--phase-s SECONDS]

Every input is checked before any sample runs (exit 2, nothing written): the
profile and its ``[tolerances]`` (:mod:`picdrive.tolerances`), the design (a
verified design of this profile), the HEX (the build of this design and
profile: its build id and profile hash), the output folder (the output rule,
:mod:`picdrive.outputs`), the Dask scheduler (it answers, it has a worker).
Then the firmware is generated from the design (and its twin library built)
once, shipped to the workers once (:mod:`picdrive.robustness.engine`), and
sample ``k`` runs the drive of seed :func:`picdrive.tolerances.sample_seed`
``(S, k)`` (:mod:`picdrive.robustness.sample`).

The study folder (``-o``):

* ``study.json`` -- what the study is (profile, tolerances, design, twin, HEX,
  seed, scenario): a later run with the same study resumes it;
* ``samples.csv`` -- one row per sample, appended as the samples complete, a task's batch at a time (an
  interrupted study resumes from the rows there; a half-written last row is
  dropped);
* ``report.md``, ``plots/``, ``worst/`` -- written when the samples are done
  (:mod:`picdrive.robustness.report`).

A folder holding another study picdrive wrote is replaced whole (the output
rule); anything else in it is refused.
"""
from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import os
import sys
import time
from pathlib import Path

from ..errors import PicdriveError

__all__ = ["register", "Study", "prepare_study", "run_study", "read_samples"]

STUDY_SCHEMA = "picdrive.robustness/1"
COMMAND = "robustness"


class Study:
    """A checked study: the nominal profile, the design, the firmware, the scenario, the folder."""

    def __init__(self, *, profile, design_path: Path, fw, plan: dict, hex_bytes: bytes | None, hex_name: str | None,
                 samples: int, seed: int, out: Path):
        self.profile, self.design_path, self.fw, self.plan = profile, design_path, fw, plan
        self.hex_bytes, self.hex_name = hex_bytes, hex_name
        self.samples, self.seed, self.out = samples, seed, out
        self.worst = 3

    @property
    def processor(self) -> bool:
        return self.hex_bytes is not None

    def identity(self) -> dict:
        """What makes two runs the same study (``study.json``); ``--samples`` is not part of it."""
        from ..tolerances import tolerances_toml
        return {"schema": STUDY_SCHEMA, "profile": self.profile.name, "profile_sha256": self.profile.sha256,
                "tolerances": tolerances_toml(self.profile.tolerances),
                "design": self.design_path.name,
                "design_sha256": hashlib.sha256(self.design_path.read_bytes()).hexdigest(),
                "firmware_build_id": f"0x{self.fw.build_id:08X}",
                "twin": "processor" if self.processor else "software",
                "hex_sha256": hashlib.sha256(self.hex_bytes).hexdigest() if self.processor else None,
                "seed": self.seed, "plan": self.plan}


# ---------------------------------------------------------------------------
# checks before any sample
# ---------------------------------------------------------------------------
def _check_hex(path: str, profile, fw) -> bytes:
    """The HEX's bytes, once it is known to be the build of this design for this profile."""
    import struct

    from picdrive_hil import pil
    from picdrive_hil.build import TwinError
    try:
        img = pil.load_image(Path(path))
    except (TwinError, OSError) as e:
        raise PicdriveError(f"--hex {path}: {e}") from None
    flash = bytes(img.flash)
    want = struct.pack("<II", fw.build_id, profile.hash32)
    if flash.find(want) < 0:
        ph = struct.pack("<I", profile.hash32)
        other = flash.find(ph)
        if other >= 4:
            bid = struct.unpack("<I", flash[other - 4:other])[0]
            why = (f"it is build 0x{bid:08X} of profile {profile.name!r}, but this design's firmware is build "
                   f"0x{fw.build_id:08X} (another design, or another picdrive version)")
        else:
            why = (f"it carries neither this design's build id 0x{fw.build_id:08X} nor the profile hash "
                   f"0x{profile.hash32:08X} (a HEX of another profile or not built by picdrive)")
        raise PicdriveError(f"--hex {path} does not match the design: {why}; build the HEX of this design with "
                            f"'picdrive firmware --profile {profile.name} --design <design> -o DIR'")
    return Path(path).read_bytes()


def prepare_study(args) -> Study:
    """Check every input (no file written): profile, tolerances, design, HEX, scenario, output folder."""
    from .. import outputs
    from ..analysis.steptest import sim_plan
    from ..firmware import codegen
    from ..profile import load_profile
    from ..result import load_design
    profile = load_profile(args.profile)
    if profile.as_built_seed is not None:
        raise PicdriveError(f"profile {args.profile} names one drive off the line ([as_built] seed = "
                            f"{profile.as_built_seed}); a study draws its own drives: give the nominal profile "
                            "(without the [as_built] section)")
    design_path = Path(args.design)
    load_design(design_path, require_usable=True, profile=profile)
    plan = dict(sim_plan(profile))
    if args.phase_s is not None:
        plan.update(t_load_s=float(args.phase_s), t_end_s=2.0 * float(args.phase_s))
    fw = codegen.generate(profile, str(design_path))
    hex_bytes = _check_hex(args.hex, profile, fw) if args.hex else None
    out = outputs.dir_output(args.output, what="study folder")
    return Study(profile=profile, design_path=design_path, fw=fw, plan=plan, hex_bytes=hex_bytes,
                 hex_name=Path(args.hex).name if args.hex else None, samples=args.samples, seed=args.seed, out=out)


# ---------------------------------------------------------------------------
# the study folder: resume or start
# ---------------------------------------------------------------------------
def read_samples(path: Path) -> list[dict]:
    """The complete rows of a ``samples.csv`` (a half-written last line is left out)."""
    from .sample import row_fields
    try:
        text = path.read_text(encoding="utf-8")
    except OSError:
        return []
    if not text.endswith("\n"):
        text = text[:text.rfind("\n") + 1]
    rows = list(csv.DictReader(io.StringIO(text)))
    if rows and list(rows[0].keys()) != row_fields():
        return []
    return [r for r in rows if None not in r.values() and r.get("sample", "").isdigit()]


def _manifest(study: Study, final: bool) -> None:
    """The folder's marker: study.json (and, when final, every file) with its digest; while samples run
    ``samples.csv`` and the report's files are declared regenerable (they grow, or are rewritten)."""
    from .. import outputs
    out = study.out
    files = {}
    for p in sorted(out.rglob("*")):
        rel = p.relative_to(out).as_posix()
        if p.is_file() and rel != outputs.MARKER and (final or rel == "study.json"):
            files[rel] = p.read_bytes()
    regen = [] if final else ["samples.csv", "report.md", "plots", "worst"]
    outputs.write_text(out / outputs.MARKER, outputs.manifest_text(COMMAND, files, regenerable=regen),
                       what="study folder marker")


def _open_folder(study: Study) -> list[dict]:
    """Start or resume the study in its folder; returns the rows already there (resume)."""
    import shutil

    from .. import outputs
    out = study.out
    ident = study.identity()
    done: list[dict] = []
    if (out / "study.json").is_file():
        try:
            old = json.loads((out / "study.json").read_text(encoding="utf-8"))
        except (OSError, ValueError):
            old = None
        if old == json.loads(json.dumps(ident)):
            done = read_samples(out / "samples.csv")
        else:
            diff = [k for k in ident if old is None or old.get(k) != json.loads(json.dumps(ident)).get(k)]
            print(f"picdrive robustness: {out} holds another study (its {', '.join(diff)} differ); replacing it",
                  file=sys.stderr)
    if not done:
        if out.exists():
            # dir_output checked that every file there is one picdrive wrote (unchanged or regenerable)
            for p in list(out.iterdir()):
                shutil.rmtree(p) if p.is_dir() and not p.is_symlink() else p.unlink()
        out.mkdir(parents=True, exist_ok=True)
        outputs.write_text(out / "study.json", json.dumps(ident, indent=1, sort_keys=True) + "\n",
                           what="study description")
    _manifest(study, final=False)
    from .sample import row_fields
    csv_path = out / "samples.csv"
    # rewrite without a half-written last line, or with the header of a new study
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=row_fields(), lineterminator="\n")
    w.writeheader()
    for r in done:
        w.writerow(r)
    outputs.write_text(csv_path, buf.getvalue(), what="sample table")
    return done


# ---------------------------------------------------------------------------
# the run
# ---------------------------------------------------------------------------
def _package(study: Study, workdir: Path):
    """The firmware package (engine.FirmwarePackage) and the folder the client built it in."""
    from .. import outputs
    from .engine import PACKAGE_FOLDER, FirmwarePackage
    fw = study.fw
    if study.processor:
        files = {"firmware.hex": study.hex_bytes, "board.json": fw.files["board.json"].encode("utf-8")}
    else:
        files = {rel: text.encode("utf-8") for rel, text in fw.files.items() if rel != outputs.MARKER}
    folder = workdir / PACKAGE_FOLDER
    for rel, data in files.items():
        p = folder / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data)
    return FirmwarePackage(files=files, profile=study.profile, table=fw.table, plan=study.plan,
                           processor=study.processor), folder


def _build_once(study: Study, folder: Path) -> None:
    """Build (or find in the cache) the twin's library on the client and start it once: a firmware or a
    HEX the twin cannot run fails the study here, before any sample."""
    from picdrive_hil.twin import Twin
    tw = Twin(study.profile, folder, hex_file=folder / "firmware.hex" if study.processor else None)
    tw.close()


def run_study(study: Study, *, scheduler: str | None, workers: int | None, progress: bool = True,
              log=None, connect_timeout_s: float | None = None) -> dict:
    """Run the study's missing samples on Dask, appending each row to ``samples.csv`` as it completes;
    then write the report.  Returns the summary (:func:`picdrive.robustness.report.summarise`)."""
    import tempfile

    from .engine import SCHEDULER_TIMEOUT_S, open_client
    from .report import summarise, write_report
    from .sample import row_fields
    log = log or (lambda msg: print(f"picdrive robustness: {msg}", file=sys.stderr, flush=True))
    # a scheduler that does not answer: exit 2 here, before anything is written
    client, cluster = open_client(scheduler, workers, timeout_s=connect_timeout_s or SCHEDULER_TIMEOUT_S)
    try:
        with tempfile.TemporaryDirectory(prefix="picdrive-robustness-") as tmp:
            pkg, folder = _package(study, Path(tmp))
            _build_once(study, folder)
            done = _open_folder(study)
            have = {int(r["sample"]) for r in done}
            todo = [k for k in range(study.samples) if k not in have]
            n_workers = len(client.scheduler_info().get("workers", {}))
            log(f"{study.samples} samples of {study.profile.name} / {study.design_path.name} on the "
                f"{'processor twin (' + study.hex_name + ')' if study.processor else 'software twin'}, "
                f"{n_workers} worker(s){', resuming: ' + str(len(have)) + ' done' if have else ''}")
            rows = [r for r in done if int(r["sample"]) < study.samples]
            t0 = time.perf_counter()
            if todo:
                rows += _run_tasks(client, pkg, study, todo, progress, row_fields())
            wall = time.perf_counter() - t0
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    rows.sort(key=lambda r: int(r["sample"]))
    summary = summarise(study, rows, wall_s=wall, n_run=len(todo), n_workers=n_workers)
    write_report(study, rows, summary)
    _manifest(study, final=True)
    return summary


def _lost_row(study: Study, fields: list[str], k: int, s: int, e: BaseException) -> dict:
    """The row of a drive whose worker failed (died, lost): an error with the reason."""
    from ..tolerances import PARAMETERS, draw
    row = {name: "" for name in fields}
    row.update(sample=k, seed=s, status="error", failed_limits="simulation",
               reason=f"the worker running it failed: {type(e).__name__}: {e}", worst_ratio="inf")
    for name, v in draw(study.profile.tolerances, s).values().items():
        row[f"dev_{name}_{'deg' if PARAMETERS[name]['unit'] == 'deg' else 'pct'}"] = round(v, 6)
    return row


def _run_tasks(client, pkg, study: Study, todo: list[int], progress: bool, fields: list[str]) -> list[dict]:
    from distributed import as_completed

    from ..tolerances import sample_seed
    from .engine import run_task
    try:
        from tqdm import tqdm
    except ImportError:                                       # pragma: no cover - tqdm is a dependency
        tqdm = None
    from .engine import batch_size
    pkg_f = client.scatter(pkg, broadcast=True)
    n_workers = max(1, len(client.scheduler_info().get("workers", {})))
    size = batch_size(len(todo), n_workers)
    batches = [todo[i:i + size] for i in range(0, len(todo), size)]
    seeds = [[sample_seed(study.seed, k) for k in b] for b in batches]
    futures = client.map(run_task, [pkg_f] * len(batches), batches, seeds, pure=False)
    batch_of = {f.key: (b, s) for f, b, s in zip(futures, batches, seeds)}
    rows = []
    bar = tqdm(total=study.samples, initial=study.samples - len(todo), desc="samples", unit="sample",
               disable=not progress, file=sys.stderr, smoothing=0.05) if tqdm else None
    with open(study.out / "samples.csv", "a", encoding="utf-8", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields, lineterminator="\n")
        for fut in as_completed(futures, loop=client.loop):
            try:
                got = fut.result()
            except Exception as e:      # noqa: BLE001 -- a worker that died running them: failed samples
                got = [_lost_row(study, fields, k, s, e) for k, s in zip(*batch_of[fut.key])]
            for row in got:
                w.writerow(row)
                rows.append({k: str(v) for k, v in row.items()})
            f.flush()
            fut.release()
            if bar is not None:
                bar.update(len(got))
    if bar is not None:
        bar.close()
    return rows


# ---------------------------------------------------------------------------
# the command
# ---------------------------------------------------------------------------
def _cmd(args) -> int:
    if args.worst < 0:
        raise PicdriveError(f"--worst {args.worst}: expected the number of worst drives to write, >= 0")
    if args.workers is not None and args.scheduler is not None:
        raise PicdriveError("--workers starts a local cluster; with --scheduler the cluster's own workers run "
                            "the study: give one of them")
    study = prepare_study(args)
    study.worst = args.worst
    s = run_study(study, scheduler=args.scheduler, workers=args.workers, progress=not args.no_progress,
                  connect_timeout_s=args.connect_timeout)
    lo, hi = s["yield_ci"]
    print(f"yield       {s['passed']}/{s['n']} = {100 * s['yield']:.1f} % (95 % interval {100 * lo:.1f} .. "
          f"{100 * hi:.1f} %, Wilson)")
    for k, v in s["failed_by_limit"].items():
        print(f"  failed    {k}: {v} sample(s)")
    if s.get("driver"):
        d = s["driver"]
        print(f"driver      {d['parameter']} (Spearman rho with failing {d['rho_fail']:+.2f}, p = {d['p_fail']:.2g})")
    if s["n_run"]:
        print(f"speed       {s['n_run']} samples in {s['wall_s']:.1f} s on {s['n_workers']} worker(s): "
              f"{s['samples_per_s']:.2f} samples/s, {s['samples_per_s_per_worker']:.2f} per worker")
    print(f"wrote {study.out / 'report.md'}")
    return 0


def register(sub) -> None:
    from ..argtypes import positive_float, seed

    def samples(text: str) -> int:
        import argparse
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if not 1 <= v <= 10_000_000:
            raise argparse.ArgumentTypeError(f"{text!r}: expected 1 .. 10000000 samples")
        return v

    def workers(text: str) -> int:
        import argparse
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if not 1 <= v <= 1024:
            raise argparse.ArgumentTypeError(f"{text!r}: expected 1 .. 1024 worker processes")
        return v

    p = sub.add_parser(
        "robustness", help="tolerance study: the design's firmware on drives drawn from the profile's tolerances",
        description="Run the design's verification scenario (step and load step, the verification's limits) on "
                    "drives drawn from the profile's [tolerances], on the software twin or (--hex) the processor "
                    "twin, distributed with Dask; writes the yield with its 95 % interval, histograms, the "
                    "parameters that drive failures and the worst drives as profiles (docs/robustness.md).")
    p.add_argument("--profile", required=True, help="profile .toml (its [tolerances]), or a bundled profile name")
    p.add_argument("--design", required=True, help="a verified design file of this profile")
    p.add_argument("--hex", help="processor twin: run this HEX (the design's build, 'picdrive firmware') on the "
                                 "PIC18 simulator instead of the firmware's C")
    p.add_argument("--samples", type=samples, required=True, help="number of drives (samples) in the study")
    p.add_argument("-o", "--output", required=True,
                   help="study folder: new, empty, or one picdrive wrote (the same study resumes)")
    p.add_argument("--seed", type=seed, default=1, help="study seed: sample k is the drive of seed (S, k) (default 1)")
    p.add_argument("--scheduler", help="address of a running Dask scheduler, tcp://HOST:PORT (default: a local "
                                       "cluster on this machine's cores)")
    p.add_argument("--connect-timeout", type=positive_float, default=None, metavar="SECONDS",
                   help="how long --scheduler has to answer and show a worker, s (default 10)")
    p.add_argument("--workers", type=workers, help="local cluster: number of worker processes (default: the cores)")
    p.add_argument("--phase-s", type=positive_float, default=None, metavar="SECONDS",
                   help="length of each phase of the scenario (step, then load step), s; the limits scale with it "
                        "(default: the verification's)")
    p.add_argument("--worst", type=int, default=3, metavar="N", help="worst drives written as profiles (default 3)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd)
