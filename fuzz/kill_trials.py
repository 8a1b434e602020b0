"""SIGKILL trials: kill a verb at random moments and check that OUT is absent, unchanged or complete.

Run::

    python fuzz/kill_trials.py calibrate --trials 20 [--seed 0] [--work DIR]
    python fuzz/kill_trials.py convert --trials 20
    python fuzz/kill_trials.py demo --trials 20
    python fuzz/kill_trials.py survey dense ortho texture --trials 6

Each verb first runs once to completion (its duration ``T`` and its complete output set are recorded).
Then every trial starts the verb in a new session, waits a seeded uniform delay in ``[0.05 T, 1.05 T]``
and sends SIGKILL to the verb's process only (as the OOM killer or ``kill -9`` would; its worker processes
are not signalled).  Odd trials start with OUT absent, even trials with OUT holding a complete earlier set
plus a user file that must survive.  After the kill the script waits up to 10 s and classifies:

* ``absent``: OUT does not exist (it did not before);
* ``unchanged``: OUT holds exactly the files it held before, byte for byte;
* ``complete``: ``OUT/<verb>-manifest.json`` says ``"complete": true`` and every file it lists exists;
* ``finished``: the verb exited on its own before the kill (counted as complete when it is);
* anything else is ``PARTIAL`` (a finding).

It also lists processes of the verb's session still running after the kill (``left``; zombies, which only
the container's PID 1 could reap, are counted apart).  Stale staging folders beside OUT are allowed (the next
run removes them) and counted.  Then the verb runs again into OUT: it must exit 0 with a complete set, the user's
file kept and no staging folder left.  Exit status 1 when any trial is PARTIAL, left a process or its rerun failed.

The inputs are real files from ``../shared/data`` (or ``$THERMOGRAMMETRY_DATA``): the thermal chessboard views
for ``calibrate``, FLIR SEQ/CSQ/R-JPEG files for ``convert``; ``demo`` runs its ``calibration-target`` section
(forked render workers). ``survey``, ``dense``, ``ortho`` and ``texture`` run on small synthetic inputs built once
in ``WORK/inputs`` by the tests' own helpers (``tests/survey_truth.py``, ``tests/test_texture_counts.py``): six
rendered frames of the small UAV scene with their TRUE poses (``cameras.json``) and its true DSM at 0.3 m for
``dense`` (``--workers 2``: a local cluster whose workers must not outlive the kill) and ``ortho``; the same six
frames without poses for ``survey`` (``--gnss none``); the three-view wall and its mesh for ``texture``. Several
verbs may be given; the exit status is 1 when any of them had a finding.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path


def _data() -> Path:
    env = os.environ.get("THERMOGRAMMETRY_DATA")
    root = Path(env) if env else Path(__file__).resolve().parents[2] / "shared" / "data"
    if not root.is_dir():
        raise SystemExit(f"data folder {root} not found; set THERMOGRAMMETRY_DATA")
    return root


def _exe() -> list[str]:
    return [sys.executable, "-m", "thermogrammetry.cli.main"]


VERBS = ("calibrate", "convert", "demo", "survey", "dense", "ortho", "texture")
SYNTHETIC = ("survey", "dense", "ortho", "texture")
TRUE_FRAMES = [16, 17, 18, 19, 20, 21]  # two of the small scene's flight lines overlap here (tests/test_interrupt.py)
_INPUTS: dict[str, Path] = {}


def build_inputs(folder: Path) -> Path:
    """The synthetic inputs of ``survey``/``dense``/``ortho``/``texture`` in ``folder`` (built once; reused when
    ``folder/ready`` exists). Returns ``folder``."""
    if (folder / "ready").is_file():
        return folder
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from survey_truth import write_true_dsm, write_true_survey
    from test_texture_counts import _write as write_wall

    scene, _ = write_true_survey(folder / "truth", frames=TRUE_FRAMES)
    write_true_dsm(folder / "dsm.tif", scene, 0.3)
    write_wall(folder / "wall")
    (folder / "ready").write_text("inputs complete\n")
    return folder


def command(verb: str, out: Path) -> list[str]:
    if verb in SYNTHETIC:
        i = _INPUTS["folder"]
        sv = i / "truth"
        if verb == "survey":
            return [*_exe(), "survey", str(sv / "frames"), "-o", str(out), "--workers", "0", "--gnss", "none",
                    "--low-texture", "off", "--input-unit", "K"]
        if verb == "dense":
            return [*_exe(), "dense", str(sv), "-o", str(out), "--workers", "2"]
        if verb == "ortho":
            return [*_exe(), "ortho", str(sv), "--dsm", str(i / "dsm.tif"), "-o", str(out), "--workers", "0"]
        return [*_exe(), "texture", str(i / "wall"), "--mesh", str(i / "wall" / "mesh.obj"), "-o", str(out),
                "--texel-size", "0.02"]
    d = _data()
    if verb == "calibrate":
        views = d / "thermal_chessboard" / "Thermal camera calibration" / "Thermal images cropped"
        return [*_exe(), "calibrate", str(views), "--target", "chessboard", "--corners", "6x5", "--spacing-mm", "100",
                "-o", str(out)]
    if verb == "convert":
        ext = d / "flir_thermimage" / "inst" / "extdata"
        return [*_exe(), "convert", str(ext / "SampleSEQ.seq"), str(ext / "SampleCSQ.csq"), str(ext / "IR_2412.jpg"),
                "-o", str(out)]
    if verb == "demo":
        return [*_exe(), "demo", str(out), "--sections", "calibration-target", "--threads", "2"]
    raise SystemExit(f"unknown verb {verb!r}; expected one of {', '.join(VERBS)}")


def snapshot(folder: Path) -> dict[str, str]:
    """Relative path -> sha256 of every file under ``folder`` ({} when absent)."""
    if not folder.exists():
        return {}
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def is_complete(out: Path, verb: str) -> bool:
    m = out / f"{verb}-manifest.json"
    try:
        doc = json.loads(m.read_text())
    except (OSError, ValueError):
        return False
    return bool(doc.get("complete")) and all((out / f).exists() for f in doc.get("files", []))


def session_processes(sid: int) -> tuple[list[int], list[int]]:
    """(running, zombie) pids whose session id is ``sid``."""
    running, zombies = [], []
    for p in Path("/proc").iterdir():
        if not p.name.isdigit():
            continue
        try:
            stat = (p / "stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()
        state, session = fields[0], int(fields[3])
        if session == sid:
            (zombies if state == "Z" else running).append(int(p.name))
    return running, zombies


def staging_left(out: Path) -> int:
    return sum(1 for p in out.parent.iterdir() if p.name.startswith(f".{out.name}.") or p.name.startswith(f"{out.name}.tmp"))


def run_trials(verb: str, trials: int, seed: int, work: Path) -> int:
    work.mkdir(parents=True, exist_ok=True)
    ref = work / "reference"
    shutil.rmtree(ref, ignore_errors=True)
    t0 = time.perf_counter()
    rc = subprocess.run(command(verb, ref), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL).returncode
    duration = time.perf_counter() - t0
    if rc != 0 or not is_complete(ref, verb):
        raise SystemExit(f"{verb}: the reference run failed (exit {rc}); nothing to trial")
    print(f"{verb}: reference run {duration:.1f} s, {len(snapshot(ref))} files")
    rng = random.Random(seed)
    counts: dict[str, int] = {}
    bad = reruns_bad = 0
    for i in range(trials):
        out = work / f"trial{i:02d}"
        shutil.rmtree(out, ignore_errors=True)
        preexisting = i % 2 == 0
        if preexisting:
            shutil.copytree(ref, out)
            (out / "user-notes.txt").write_text("a file of the user's that must survive\n")
        before = snapshot(out)
        delay = rng.uniform(0.05, 1.05) * duration
        proc = subprocess.Popen(command(verb, out), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                start_new_session=True)
        try:
            proc.wait(timeout=delay)
            finished = True
        except subprocess.TimeoutExpired:
            finished = False
            proc.send_signal(signal.SIGKILL)
            proc.wait()
        running: list[int] = []
        zombies: list[int] = []
        for _ in range(40):  # workers notice their parent's death within a poll interval
            running, zombies = session_processes(proc.pid)
            if not running:
                break
            time.sleep(0.25)
        after = snapshot(out)
        if finished:
            state = "finished" if is_complete(out, verb) else "PARTIAL"
        elif not preexisting and not out.exists():
            state = "absent"
        elif after == before:
            state = "unchanged"
        elif is_complete(out, verb):
            state = "complete"
        else:
            state = "PARTIAL"
        if preexisting and "user-notes.txt" not in after:
            state = "PARTIAL (user file lost)"
        counts[state] = counts.get(state, 0) + 1
        left = len(running)
        bad += state.startswith("PARTIAL") or left > 0
        for pid in running:  # do not leave them to the next trial
            try:
                os.kill(pid, signal.SIGKILL)
            except OSError:
                pass
        stale = staging_left(out)
        rerun = rerun_completes(verb, out, preexisting)
        reruns_bad += not rerun
        bad += not rerun
        print(f"  trial {i:2d}: OUT {'existed' if preexisting else 'absent '} kill at {delay:6.1f} s -> {state:10s} "
              f"processes left {left}, zombies {len(zombies)}, staging folders {stale}; "
              f"rerun {'complete' if rerun else 'FAILED'}")
    print(f"{verb}: {trials} trials: " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items()))
          + f"; reruns not complete: {reruns_bad}; trials with a partial OUT, a process left or a failed rerun: {bad}")
    return 1 if bad else 0


def rerun_completes(verb: str, out: Path, preexisting: bool) -> bool:
    """Run the verb again into ``out`` after a kill: exit 0, a complete set, the user's file kept (when there was one)
    and no staging folder of the killed run left beside OUT."""
    rc = subprocess.run(command(verb, out), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL).returncode
    kept = not preexisting or (out / "user-notes.txt").is_file()
    return rc == 0 and is_complete(out, verb) and kept and staging_left(out) == 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("verb", nargs="+", choices=VERBS)
    ap.add_argument("--trials", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work", type=Path, default=None, help="scratch folder (default: a new temporary folder)")
    a = ap.parse_args(argv)
    import tempfile

    work = a.work or Path(tempfile.mkdtemp(prefix=f"kill-{'-'.join(a.verb)}-"))
    if any(v in SYNTHETIC for v in a.verb):
        _INPUTS["folder"] = build_inputs(work / "inputs")
    status = 0
    for verb in a.verb:
        status |= run_trials(verb, a.trials, a.seed, work / verb)
    return status


if __name__ == "__main__":
    raise SystemExit(main())
