"""Shared test set-up: strict numpy rank promotion, keys, a compilation cache.

The suite compiles the same programs many times (the main job is run again to
resume it, the same tiny configs train in several tests, and every subprocess
starts a fresh JAX), and XLA compilation is most of its time on a 2-core CPU. So
the test session uses JAX's persistent compilation cache in a directory of its
own: made empty for each session (no state survives between runs), shared by the
pytest-xdist workers and, through the environment, by the subprocesses the tests
start. Every program is cached, however small: code run eagerly (model
initialisation, tests that call a function outside jit) compiles one program per
operation and shape, each in a fraction of a second, and every process would
compile them again. A cache hit returns the executable the compiler made for the
identical program, so no test checks anything different; the library itself never
turns the cache on.
"""

import os
import shutil
import tempfile

import jax
import pytest
from hypothesis import HealthCheck, settings

jax.config.update("jax_numpy_rank_promotion", "raise")

# Property tests (tests/property_test.py): the same examples on every run (derandomised,
# no example database written into the clone), no per-example deadline (the first example
# of a test compiles), a budget that keeps the suite within its time.
settings.register_profile(
    "c3dpo", derandomize=True, database=None, deadline=None, max_examples=60,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
# HYPOTHESIS_PROFILE=thorough: fresh random draws, many more of them (a search, not CI).
settings.register_profile("thorough", parent=settings.get_profile("c3dpo"), derandomize=False,
                          max_examples=1000)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "c3dpo"))


_MADE_CACHE_DIR = None  # set in the process that made the directory (it removes it)


def _compilation_cache_dir() -> str:
    # xdist workers inherit the controller's environment: the first process of the
    # session makes the directory, the workers and subprocesses reuse it.
    global _MADE_CACHE_DIR
    path = os.environ.get("JAX_COMPILATION_CACHE_DIR")
    if not path:
        path = _MADE_CACHE_DIR = tempfile.mkdtemp(prefix="c3dpo_jax_test_xla_cache_")
        os.environ["JAX_COMPILATION_CACHE_DIR"] = path
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
    return path


jax.config.update("jax_compilation_cache_dir", _compilation_cache_dir())
jax.config.update("jax_persistent_cache_min_compile_time_secs",
                  float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"]))


def pytest_sessionfinish(session, exitstatus):
    if _MADE_CACHE_DIR is not None:  # the controller, after every worker has finished
        shutil.rmtree(_MADE_CACHE_DIR, ignore_errors=True)


@pytest.fixture
def smoke_subprocess_env():
    """``make(*xla_flags) -> env`` for subprocesses that train smoke-sized models.

    Their time is mostly XLA compilation, which LLVM optimisation level 0 about halves
    (their runtime is negligible); the flags are appended to the caller's XLA_FLAGS.
    In-process tests keep compiling the training step as users do.
    """

    def make(*xla_flags: str) -> dict[str, str]:
        flags = [os.environ.get("XLA_FLAGS", ""), *xla_flags, "--xla_backend_optimization_level=0"]
        return dict(os.environ, XLA_FLAGS=" ".join(f for f in flags if f))

    return make


@pytest.fixture(scope="session")
def load_script():
    """``load(path) -> module``: a script of the repository (``experiments/...``, which is
    not a package) imported from its path relative to the repository root."""
    import importlib.util

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

    def load(path: str):
        name = path.removesuffix(".py").replace("/", "_")
        spec = importlib.util.spec_from_file_location(name, os.path.join(root, path))
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load


@pytest.fixture(scope="session")
def read_scalars():
    """``read(logdir) -> {tag: [(step, value), ...]}``: the TensorBoard curves of a folder's
    event files as TensorBoard shows them (its own reader, ``EventAccumulator``, which
    applies a resumed run's purge of the steps it replays)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    def read(logdir) -> dict[str, list[tuple[int, float]]]:
        events = EventAccumulator(str(logdir), size_guidance={"scalars": 0})  # 0: every point
        events.Reload()
        return {tag: [(e.step, e.value) for e in events.Scalars(tag)]
                for tag in events.Tags()["scalars"]}

    return read


@pytest.fixture
def key():
    return jax.random.key(0)
