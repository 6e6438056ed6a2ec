"""A sweep across two Ray nodes, tested for real, and a node lost in the middle of it.

``experiments/ray_two_nodes.sh`` turns this machine into two: two network namespaces joined by a
veth pair (the head at 10.231.0.1, the worker at 10.231.0.2, no route anywhere else, so the
cluster's traffic stays between the two), each node's processes under a hostname of their own, and
Ray's token authentication on every node and every launching process. The tests drive the script
(``up``, ``on``, ``kill-raylet``, ``down``) and check that

- a sweep launched on the head through the cluster address, and one launched on the worker machine
  through the Ray Client address, run experiments on both nodes (each file's ``/versions`` ``host``)
  and write the files the local backend writes;
- a driver without the cluster's token is refused;
- when the worker node's raylet is killed while it runs an experiment, Ray runs that task again on
  the head, which resumes the experiment from its file: every finished trial is kept, the sweep
  finishes, and running the same command again leaves results equal to an uninterrupted sweep's;
- nothing is left behind (namespaces, the veth pair, processes), also when setting up fails.

Where network namespaces cannot be made (not root, no ``ip`` or ``unshare``, a kernel or container
that refuses) the cluster tests skip and say why. The fake-Ray tests at the end check the Ray
backend's handling of a lost task and of a file its node wrote where the launcher cannot see it.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from pipps.experiments.results import read_result

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "experiments" / "ray_two_nodes.sh"
HEAD_ADDRESS = "10.231.0.1:6379"
CLIENT_ADDRESS = "ray://10.231.0.1:10001"
# two experiments of three trials each (quick preset, tiny budgets): one per node
SWEEP = ["--table", "4.1", "--k", "1", "--methods", "tp", "--seeds", "2", "--preset", "quick",
         "--set", "num_particles=8", "--set", "num_learned=2", "--set", "policy_evals=6",
         "--set", "eval_rollouts=3", "--set", "gp_max_iters=10", "--jobs", "2"]
_names = itertools.count()


def namespaces_unavailable() -> str | None:
    """Why two machines cannot be made here, or None."""
    if not sys.platform.startswith("linux"):
        return "network namespaces are a Linux feature"
    if os.geteuid() != 0:
        return "making network namespaces needs root"
    for tool in ("ip", "unshare"):
        if shutil.which(tool) is None:
            return f"no `{tool}` command"
    probe = f"pipps-probe-{os.getpid()}"
    made = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if made.returncode != 0:
        return f"`ip netns add` refused: {made.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    uts = subprocess.run(["unshare", "--uts", "true"], capture_output=True, text=True)
    if uts.returncode != 0:
        return f"`unshare --uts` refused: {uts.stderr.strip()}"
    return None


def needs_namespaces():
    reason = namespaces_unavailable()
    if reason:
        pytest.skip(reason)


class Machines:
    """The two machines of one ``experiments/ray_two_nodes.sh`` cluster (``up`` or not yet)."""

    def __init__(self, state: Path, python: str = sys.executable):
        self.name = f"pipps-t{os.getpid()}-{next(_names)}"
        self.state = state
        self.env = {**os.environ, "PIPPS_CLUSTER_DIR": str(state), "PIPPS_CLUSTER_NAME": self.name,
                    "PYTHON": python, "JAX_PLATFORMS": "cpu"}
        self.env.pop("RAY_ADDRESS", None)
        self.host = {"head": f"{self.name}-head", "worker": f"{self.name}-worker"}  # also the namespaces' names

    def script(self, *args, timeout=300, check=True, **kw) -> subprocess.CompletedProcess:
        return subprocess.run(["bash", str(SCRIPT), *map(str, args)], env=self.env, cwd=REPO, text=True,
                              capture_output=True, timeout=timeout, check=check, **kw)

    def sweep_command(self, machine: str, address: str, out: Path) -> list[str]:
        return ["bash", str(SCRIPT), "on", machine, sys.executable, "-m", "pipps.cli", "sweep", *SWEEP,
                "--backend", "ray", "--address", address, "--out", str(out)]

    def sweep(self, machine: str, address: str, out: Path) -> subprocess.CompletedProcess:
        return subprocess.run(self.sweep_command(machine, address, out), env=self.env, cwd=REPO, text=True,
                              capture_output=True, timeout=600)

    def namespace_inodes(self) -> set[int]:
        found = set()
        for host in self.host.values():
            with contextlib.suppress(FileNotFoundError):
                found.add(os.stat(f"/run/netns/{host}").st_ino)
        return found

    def leftovers(self, inodes: set[int]) -> list[str]:
        """What is left of the machines: their namespaces, processes in them or naming the state folder."""
        listed = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout.split()
        left = [f"namespace {n}" for n in self.host.values() if n in listed or os.path.exists(f"/run/netns/{n}")]
        for proc in Path("/proc").iterdir():
            if not proc.name.isdigit():
                continue
            try:
                net = os.readlink(proc / "ns" / "net")
                cmdline = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            except OSError:  # gone meanwhile
                continue
            if any(net == f"net:[{ino}]" for ino in inodes) or str(self.state) in cmdline:
                left.append(f"process {proc.name}: {cmdline[:200]}")
        return left


@contextlib.contextmanager
def two_machines(python: str = sys.executable):
    """Two machines with a Ray node each (``ray_two_nodes.sh up``), taken down on the way out, also
    when setting up or the body fails; raises when anything of them is left."""
    needs_namespaces()
    pytest.importorskip("ray")
    state = Path(tempfile.mkdtemp(prefix="pipps-rc-", dir="/tmp"))  # Ray's socket paths: < 108 characters
    machines = Machines(state, python)
    inodes: set[int] = set()
    try:
        try:
            machines.script("up", timeout=300)
        finally:
            inodes = machines.namespace_inodes()
        yield machines
    finally:
        inodes |= machines.namespace_inodes()
        down = machines.script("down", timeout=120, check=False)
        left = machines.leftovers(inodes)
        shutil.rmtree(state, ignore_errors=True)
        assert down.returncode == 0 and not left, f"teardown left {left}; `down` said: {down.stderr[-2000:]}"


def hosts(folder: Path) -> dict[str, str]:
    """Each result file's name and the node that wrote it."""
    out = {}
    for path in sorted(folder.glob("*.h5")):
        with h5py.File(path) as f:
            out[path.name] = str(f["versions"].attrs["host"])
    return out


def assert_same_files(folder: Path, reference: Path) -> None:
    """The same result files as the reference folder, trial for trial (what the single-node Ray test
    checks, and the observations and costs besides)."""
    names = sorted(p.name for p in reference.glob("*.h5"))
    assert names and sorted(p.name for p in folder.glob("*.h5")) == names
    for name in names:
        a, b = read_result(reference / name), read_result(folder / name)
        assert a.status == b.status == "complete"
        assert a.config == b.config and len(a.trials) == len(b.trials)
        for ta, tb in zip(a.trials, b.trials):
            for field in ("states", "observations", "actions", "costs", "eval_returns", "policy"):
                np.testing.assert_array_equal(getattr(ta, field), getattr(tb, field), err_msg=f"{name} {field}")


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    """The sweep on the local backend: what the cluster must write."""
    needs_namespaces()
    out = tmp_path_factory.mktemp("local")
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": os.pathsep.join(filter(None, [
        str(REPO), os.environ.get("PYTHONPATH")]))}
    proc = subprocess.run([sys.executable, "-m", "pipps.cli", "sweep", *SWEEP, "--out", str(out)], env=env, cwd=REPO,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out


@pytest.mark.slow  # ~2.5 min here (2 busy CPUs): the nodes start, two sweeps of two experiments, a refused driver
class TestTwoNodes:
    @pytest.fixture(scope="class")
    def cluster(self):
        with two_machines() as machines:
            yield machines

    @pytest.mark.parametrize("machine, address", [("head", HEAD_ADDRESS), ("worker", CLIENT_ADDRESS)],
                             ids=["cluster-address-from-the-head", "ray-client-from-the-worker"])
    def test_a_sweep_runs_on_both_nodes_and_writes_the_local_backends_files(self, cluster, reference, tmp_path,
                                                                            machine, address):
        out = tmp_path / "runs"
        proc = cluster.sweep(machine, address, out)
        assert proc.returncode == 0, proc.stderr[-3000:]
        assert "ran 2, skipped 0" in proc.stdout
        assert sorted(hosts(out).values()) == sorted(cluster.host.values())  # one experiment on each node
        assert_same_files(out, reference)

    def test_a_driver_without_the_clusters_token_is_refused(self, cluster, tmp_path):
        wrong = tmp_path / "token"
        wrong.write_text("not-the-clusters-token")
        proc = cluster.script("on", "worker", "env", f"RAY_AUTH_TOKEN_PATH={wrong}", sys.executable, "-c",
                              f"import ray; ray.init(address={HEAD_ADDRESS!r}); print('connected')", check=False)
        assert proc.returncode != 0 and "connected" not in proc.stdout
        assert "Failed to connect to Ray cluster" in proc.stderr


@pytest.mark.slow  # ~1.5 min here
def test_a_node_lost_mid_sweep_loses_no_finished_trial_and_the_sweep_finishes_on_the_other(reference, tmp_path):
    """The worker node's raylet is killed once an experiment it runs has finished a trial. Its worker
    process exits with it (it lost its raylet) and so releases the file's lock; the GCS marks the
    node dead, and Ray runs the task again (ray_task's retries) on the head, once the head's CPU is
    free, where it resumes the experiment after its last finished trial. The sweep ends normally;
    running it again runs nothing, and the files equal the local backend's."""
    out = tmp_path / "runs"
    with two_machines() as machines:
        command = machines.sweep_command("head", HEAD_ADDRESS, out)
        log = tmp_path / "sweep.log"
        with open(log, "w") as sink:
            sweep = subprocess.Popen(command, env=machines.env, cwd=REPO, text=True, stdout=sink, stderr=sink)
            try:
                lost, seen = None, 0
                deadline = time.monotonic() + 480
                while lost is None and sweep.poll() is None and time.monotonic() < deadline:
                    for path in out.glob("*.h5"):
                        with contextlib.suppress(OSError, KeyError):  # replaced while read: look again
                            with h5py.File(path) as f:
                                if (f["versions"].attrs["host"] == machines.host["worker"]
                                        and f.attrs["status"] == "running" and f.attrs["num_trials_done"] >= 1):
                                    lost, seen = path, int(f.attrs["num_trials_done"])
                    time.sleep(0.1)
                assert lost is not None, f"never caught the worker mid-experiment:\n{log.read_text()[-3000:]}"
                killed = machines.script("kill-raylet", "worker")
                assert "killed the raylet of worker" in killed.stdout
                code = sweep.wait(timeout=600)
            finally:
                if sweep.poll() is None:
                    sweep.kill()
                    sweep.wait()
        text = log.read_text()
        assert code == 0, text[-3000:]
        assert "ran 2, skipped 0 (complete, or running in another process), failed 0" in text
        result = read_result(lost)
        assert result.status == "complete"
        assert result.resumed_at and result.resumed_at[0] >= seen  # the finished trials were kept, not rerun
        assert hosts(out)[lost.name] == machines.host["head"]  # finished on the node still alive
        stamps = {p.name: p.stat().st_mtime_ns for p in out.glob("*.h5")}
        again = subprocess.run(command, env=machines.env, cwd=REPO, text=True, capture_output=True, timeout=600)
        assert again.returncode == 0, again.stderr[-3000:]
        assert "ran 0, skipped 2" in again.stdout
        assert {p.name: p.stat().st_mtime_ns for p in out.glob("*.h5")} == stamps
    assert_same_files(out, reference)


def test_the_machines_are_removed_also_when_setting_up_fails():
    """``up`` fails after making the namespaces (no interpreter to start Ray with): both go."""
    with pytest.raises(subprocess.CalledProcessError):
        with two_machines(python="/bin/false"):
            pass  # pragma: no cover - never reached


# -- the Ray backend's bookkeeping, with a stand-in for Ray ----------------------------------------


class FakeRay:
    """Just enough of Ray for ``_run_on_ray``: tasks run at once, in this process, unpinned."""

    class exceptions:
        class RayError(Exception):
            pass

    def __init__(self):
        self.options, self.names = {}, []

    def is_initialized(self):
        return True

    def remote(self, **options):
        self.options = options
        fake = self

        class Task:
            def options(self, name):
                fake.names.append(name)
                return self

            def remote(self, fn, *args):
                try:
                    return ("done", fn(*args))
                except Exception as err:
                    return ("raised", err)

        return lambda fn: Task()

    def wait(self, refs, num_returns):
        return refs[:1], refs[1:]

    def get(self, ref):
        kind, value = ref
        if kind == "raised":
            raise value
        return value


def test_ray_tasks_are_named_retried_and_checked_for_a_file_the_launcher_sees(monkeypatch, tmp_path):
    from pipps.experiments import sweep
    from pipps.experiments.config import resolve_config

    fake = FakeRay()
    cfgs = [resolve_config("quick", "cartpole_swingup", seed=s) for s in range(3)]
    todo = [(cfg, tmp_path / f"{sweep.experiment_name(cfg)}.h5") for cfg in cfgs]
    todo[0][1].write_bytes(b"written")  # seed 0's file is here; seed 1's task "wrote" it on its node only

    def run_one(cfg, path):
        if cfg.seed == 2:
            raise fake.exceptions.RayError("Task failed because the node it was running on is dead\nmore detail")
        return path, "ran", ""

    monkeypatch.setattr(sweep, "_run_one", run_one)
    records = []
    sweep._run_on_ray(fake, todo, 2, None, lambda *r: records.append(r))
    assert fake.options["max_retries"] == sweep.RAY_RETRIES and fake.options["num_cpus"] == 1
    assert fake.names == [f"pipps {p.name}" for _, p in todo]
    (p0, o0, _), (p1, o1, m1), (p2, o2, m2) = records
    assert (p0, o0) == (str(todo[0][1]), "ran")
    assert o1 == "failed" and m1.startswith(f"OutputError: node {os.uname().nodename} wrote ")
    assert "--out must be a folder that every node and the launching machine share" in m1
    assert o2 == "failed" and m2 == ("RayError: Task failed because the node it was running on is dead (the file "
                                     "keeps every finished trial; running the same sweep again resumes it)")
