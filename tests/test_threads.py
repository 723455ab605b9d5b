"""A simulator serves one thread at a time: a second thread that ticks or resets it while
another is inside gets ConcurrentUseError at once; it never hangs and never crashes.

Each case runs in a subprocess with a timeout, so that a regression (a hang in the helper
threads' join, or a segfault) fails the test instead of stopping the suite."""

import json
import subprocess
import sys
import textwrap

import pytest

CASE = textwrap.dedent("""
    import json, sys, threading
    import numpy as np
    import gymnasium as gym
    import downwash_envs
    from downwash_core.errors import ConcurrentUseError

    kind, n_threads = sys.argv[1], int(sys.argv[2])
    if kind == "vector":
        env = gym.make_vec("downwash/Follower-v2", num_envs=8, vectorization_mode="vector_entry_point",
                           n_threads=n_threads)
        action = np.zeros((8, 3), np.float32)
    else:
        env = gym.make("downwash/Follower-v2")
        action = np.zeros(3, np.float32)
    env.reset(seed=0)
    errors, others = [], []
    start = threading.Barrier(2)

    def work():
        start.wait()
        for _ in range(300):
            try:
                env.step(action)
            except ConcurrentUseError as e:
                errors.append(str(e))
                return
            except Exception as e:  # anything else is a bug
                others.append(repr(e))
                return

    threads = [threading.Thread(target=work) for _ in range(2)]
    [t.start() for t in threads]
    [t.join() for t in threads]
    env.step(action)  # the env still works for the thread that keeps it
    print(json.dumps({"errors": errors, "others": others}))
""")


@pytest.mark.parametrize("kind, n_threads", [("vector", 0), ("vector", 1), ("single", 0)])
def test_a_second_thread_gets_a_clear_error_not_a_hang(kind, n_threads):
    proc = subprocess.run([sys.executable, "-c", CASE, kind, str(n_threads)], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]  # no segfault, no hang (the timeout would raise)
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["others"] == []
    assert out["errors"], "two threads stepped one env 300 times each without ever overlapping"
    assert all("one thread at a time" in e and "one env" in e for e in out["errors"])


def test_one_env_per_thread_is_fine():
    """The rule's other side: two envs, one per thread, step side by side without an error."""
    code = textwrap.dedent("""
        import threading
        import numpy as np
        import gymnasium as gym
        import downwash_envs
        envs = [gym.make_vec("downwash/Follower-v2", num_envs=4, vectorization_mode="vector_entry_point")
                for _ in range(2)]
        for e in envs:
            e.reset(seed=0)
        def work(e):
            for _ in range(100):
                e.step(np.zeros((4, 3), np.float32))
        threads = [threading.Thread(target=work, args=(e,)) for e in envs]
        [t.start() for t in threads]
        [t.join() for t in threads]
        print("ok")
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0 and proc.stdout.strip().endswith("ok"), proc.stderr[-3000:]


def test_thread_counts_are_checked_and_default_to_the_usable_cores():
    from downwash_core.errors import ConfigError
    from sim.physics import resolve_threads, usable_cores

    cores = usable_cores()
    assert resolve_threads(0) == cores and resolve_threads(1) == 1 and resolve_threads(cores) == cores
    for bad in (-1, cores + 1, 1000, 1.5, "2", True, None):
        with pytest.raises(ConfigError, match=r"n_threads: expected 0 .* or 1\.\."):
            resolve_threads(bad)
    with pytest.raises(ConfigError, match="n_threads"):  # before any world is built
        import gymnasium as gym

        import downwash_envs  # noqa: F401

        gym.make_vec("downwash/Follower-v2", num_envs=4, vectorization_mode="vector_entry_point", n_threads=1000)


@pytest.mark.skipif(not hasattr(__import__("os"), "sched_setaffinity"), reason="CPU affinity is Linux's")
def test_the_default_follows_the_cpu_affinity():
    """A process pinned to one core (taskset, a container's cpuset) steps on one thread."""
    code = textwrap.dedent("""
        import os
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
        import numpy as np
        from sim.physics import make_physics
        from sim.scene import build_scene
        ph = make_physics(build_scene().model, 8)
        print(ph.batch.nthread)
    """)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.strip().splitlines()[-1] == "1"
