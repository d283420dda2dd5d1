"""Distributed tuning: worker processes sharing one study on a real PostgreSQL server (loopback, temp dir).

The server is Debian's PostgreSQL, started by the fixture (as the ``postgres`` user when running as root);
``scripts/ci_postgres.sh`` installs it when missing. The tests skip only when it cannot be installed.
"""

from __future__ import annotations

import os
import pwd
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

pytest.importorskip("optuna", reason="needs Optuna (the 'tune' extra)")
pytest.importorskip("sqlalchemy", reason="needs SQLAlchemy (the 'tune' extra)")

import optuna
from optuna.trial import TrialState

from diamond_sss.cli.tune_commands import tune
from diamond_sss.data.analytic import make_capture
from diamond_sss.tuning.study import StudySettings, make_storage

ROOT = Path(__file__).resolve().parents[1]
TINY_SETS = ["num_gaussians=64", "init=random", "batch_size=1", "lambda_sil=0", "lambda_depth=0",
             "raytrace_every=1000", "raytrace_gaussians=16", "raytrace_directions=2", "densify=false"]
HEARTBEAT = 2  # seconds; a trial silent for 2 x HEARTBEAT is taken for dead
ITERATIONS = 60  # steps per trial: long enough (about a second even on an idle machine) to be killed mid-trial
FINISHED = (TrialState.COMPLETE, TrialState.PRUNED)


def _postgres_bin() -> Path | None:
    found = shutil.which("pg_ctl")
    if found:
        return Path(found).resolve().parent
    installed = sorted(Path("/usr/lib/postgresql").glob("*/bin/pg_ctl"), key=lambda p: int(p.parts[-3]))
    return installed[-1].parent if installed else None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def postgres_url():
    pytest.importorskip("psycopg2", reason="psycopg2 is not installed (the 'tune' extra)")
    bin_dir = _postgres_bin()
    if bin_dir is None:
        setup = subprocess.run(["bash", str(ROOT / "scripts" / "ci_postgres.sh")], check=False,
                               capture_output=True, text=True)
        bin_dir = _postgres_bin()
        if bin_dir is None:
            pytest.skip(f"PostgreSQL cannot be installed: {(setup.stdout + setup.stderr)[-400:]}")
    run_as: list[str] = []
    base = Path(tempfile.mkdtemp(prefix="diamond_sss_pg_"))
    if os.geteuid() == 0:  # postgres refuses to run as root
        try:
            user = pwd.getpwnam("postgres")
        except KeyError:
            pytest.skip("running as root and there is no 'postgres' user to run the server as")
        os.chown(base, user.pw_uid, user.pw_gid)
        run_as = ["runuser", "-u", "postgres", "--"]
    data, port = base / "data", _free_port()
    subprocess.run([*run_as, str(bin_dir / "initdb"), "-D", str(data), "-U", "postgres", "--auth=trust",
                    "--no-sync", "-E", "UTF8"], check=True, capture_output=True)
    options = f"-p {port} -k {base} -c listen_addresses=127.0.0.1 -c fsync=off"
    subprocess.run([*run_as, str(bin_dir / "pg_ctl"), "-D", str(data), "-l", str(base / "server.log"), "-w",
                    "-t", "60", "-o", options, "start"], check=True, capture_output=True)
    try:
        yield f"postgresql://postgres@127.0.0.1:{port}/postgres"  # the tune extra's driver is chosen
    finally:
        subprocess.run([*run_as, str(bin_dir / "pg_ctl"), "-D", str(data), "-m", "immediate", "stop"],
                       check=False, capture_output=True)
        shutil.rmtree(base, ignore_errors=True)


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    root = tmp_path_factory.mktemp("tune_pg_capture")
    make_capture(root, views=4, lights=3, size=12)
    return root


def _start_worker(capture: Path, out: Path, url: str, study: str, worker: int, trials: int,
                  iterations: int) -> subprocess.Popen:
    out.mkdir(parents=True, exist_ok=True)
    command = [sys.executable, "-m", "diamond_sss.cli.tune_commands", "--data", str(capture),
               "--out", str(out), "--storage", url, "--study", study, "--trials", str(trials),
               "--iterations", str(iterations), "--report-every", "1", "--validation-images", "1",
               "--worker", str(worker), "--device", "cpu", "--heartbeat-interval", str(HEARTBEAT),
               *[arg for item in TINY_SETS for arg in ("--set", item)]]
    log = open(out / "worker.log", "w")  # noqa: SIM115 (closed with the process)
    return subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT)


def _finish(process: subprocess.Popen, out: Path, timeout: float = 240) -> None:
    process.wait(timeout=timeout)
    assert process.returncode == 0, (out / "worker.log").read_text()[-3000:]


def _pid(trial) -> int:
    return int(trial.user_attrs["worker"].rsplit(":", 1)[1])


@pytest.fixture(scope="module")
def shared_study(postgres_url, capture, tmp_path_factory):
    """Workers A and B start together on an empty database; A is killed (SIGKILL) in the middle of a trial,
    and a worker R is restarted at once (in this process) while B goes on. Returns what happened."""
    n_trials, base = 4, tmp_path_factory.mktemp("shared_study")
    a, b = (_start_worker(capture, base / name, postgres_url, "shared", w, n_trials, ITERATIONS)
            for w, name in ((0, "a"), (1, "b")))
    storage = make_storage(StudySettings(storage=postgres_url, heartbeat_interval=HEARTBEAT))
    deadline, victim = time.monotonic() + 180, None
    while victim is None:
        log = (base / "a" / "worker.log").read_text()[-3000:]
        assert a.poll() is None and time.monotonic() < deadline, log
        time.sleep(0.05)
        try:
            running = optuna.load_study(study_name="shared", storage=storage).get_trials(
                deepcopy=False, states=(TrialState.RUNNING,))
        except KeyError:  # not created yet
            continue
        victim = next((t for t in running if t.intermediate_values and _pid(t) == a.pid), None)
    a.kill()  # no clean-up: the trial stays RUNNING until its heartbeat is stale
    a.wait()
    state_after_kill = optuna.load_study(study_name="shared", storage=storage).trials[victim.number].state
    tune(capture, base / "r", trials=n_trials, storage=postgres_url, study="shared", iterations=ITERATIONS,
         report_every=1, validation_images=1, worker=2, device="cpu", heartbeat_interval=HEARTBEAT,
         set_=TINY_SETS)
    _finish(b, base / "b")
    trials = optuna.load_study(study_name="shared", storage=storage).trials
    return {"n_trials": n_trials, "trials": trials, "victim": victim.number,
            "state_after_kill": state_after_kill, "pids": {"a": a.pid, "b": b.pid, "r": os.getpid()},
            "out": base}


def test_workers_share_one_study_without_losing_or_duplicating_trials(shared_study):
    trials, pids = shared_study["trials"], shared_study["pids"]
    assert [t.number for t in trials] == list(range(len(trials)))
    assert not [t for t in trials if t.state in (TrialState.RUNNING, TrialState.WAITING)]
    finished = [t for t in trials if t.state in FINISHED]
    n_trials = shared_study["n_trials"]
    assert n_trials <= len(finished) <= n_trials + 1  # two last trials started at one instant may overshoot
    assert [t.number for t in trials if t not in finished] == [shared_study["victim"]]
    assert len({tuple(sorted(t.params.items())) for t in finished}) == len(finished)  # none ran twice
    presets = [t.user_attrs.get("preset") for t in finished]
    assert presets.count("sss3dgs") == 1 and presets.count("diamond") == 1
    workers = {_pid(t) for t in finished}
    assert {pids["b"], pids["r"]} <= workers <= set(pids.values())
    for name in ("b", "r"):
        assert (shared_study["out"] / name / "tab4.md").is_file()
        assert (shared_study["out"] / name / "best_config.json").is_file()


def test_a_killed_worker_leaves_the_study_usable_and_its_trial_is_rerun(shared_study):
    trials, pids = shared_study["trials"], shared_study["pids"]
    killed = trials[shared_study["victim"]]
    assert shared_study["state_after_kill"] == TrialState.RUNNING
    assert killed.state == TrialState.FAIL and "failure" not in killed.user_attrs
    retries = [t for t in trials if t.system_attrs.get("failed_trial") == killed.number]
    assert len(retries) == 1 and retries[0].state in FINISHED and retries[0].params == killed.params
    assert _pid(retries[0]) in (pids["b"], pids["r"])
    assert any(_pid(t) == pids["r"] for t in trials if t.state in FINISHED)  # the restarted worker took part
