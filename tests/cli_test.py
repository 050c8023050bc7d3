"""The commands' plumbing (c3dpo_jax/cli.py): bundled configs found from any directory, quiet
logs, one-line errors. The wheel and its installation: tests/install_test.py."""

import ast
import importlib.util
import logging
import os
import re
import shutil
import subprocess
import sys

import pytest
from absl import flags

from c3dpo_jax import cli

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BUNDLED_SYNTHETIC = os.path.join(cli.bundled_configs_dir(), "synthetic.py")


@pytest.fixture
def clean_configs_modules():
    """Puts back the ``configs`` modules the test replaced (other tests import them)."""
    saved = {n: m for n, m in sys.modules.items() if n == "configs" or n.startswith("configs.")}
    yield
    for name in [n for n in sys.modules if n == "configs" or n.startswith("configs.")]:
        del sys.modules[name]
    sys.modules.update(saved)


def _load_like_config_flags(path):
    """What ml_collections' config_flags does with --config=PATH: execute the file by path."""
    spec = importlib.util.spec_from_file_location("config_config", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_bundled_configs_are_the_repository_configs_in_a_checkout():
    assert cli.bundled_configs_dir() == os.path.join(ROOT, "configs")


def test_config_paths_resolve_to_the_bundled_copy_only_when_missing(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert cli.resolve_config("configs/synthetic.py:smoke") == BUNDLED_SYNTHETIC + ":smoke"
    assert cli.resolve_config("./configs/synthetic.py") == BUNDLED_SYNTHETIC
    (tmp_path / "configs").mkdir()
    (tmp_path / "configs" / "synthetic.py").write_text("from other import get_config\n")
    assert cli.resolve_config("configs/synthetic.py:smoke") == "configs/synthetic.py:smoke"
    with pytest.raises(FileNotFoundError, match="'configs/nope.py' not found.*configs/up3d.py"):
        cli.resolve_config("configs/nope.py")
    # The helpers that configs import are neither listed nor taken for configs.
    with pytest.raises(FileNotFoundError) as listing:
        cli.resolve_config("configs/nope.py")
    assert "configs/release.py" not in str(listing.value)
    assert "configs/own_json.py" in str(listing.value)
    with pytest.raises(ValueError, match=r"^configs/release.py defines no get_config\(\)"):
        cli.resolve_config("configs/release.py")
    (tmp_path / "configs" / "helper.py").write_text("def get_config_of(x):\n    return x\n")
    with pytest.raises(ValueError, match="configs/helper.py defines no get_config"):
        cli.resolve_config("configs/helper.py")
    with pytest.raises(FileNotFoundError, match="'other/synthetic.py' not found"):
        cli.resolve_config("other/synthetic.py")


def test_argv_resolution_keeps_overrides_and_other_flags(tmp_path, monkeypatch,
                                                         clean_configs_modules):
    monkeypatch.chdir(tmp_path)
    argv = ["prog", "--config", "configs/synthetic.py:smoke", "--config.seed=3", "--workdir=w"]
    assert cli._resolve_config_argv(argv) == [
        "prog", "--config", BUNDLED_SYNTHETIC + ":smoke", "--config.seed=3", "--workdir=w"]
    assert cli._resolve_config_argv(["prog", "--config=configs/up3d.py"])[1] == (
        "--config=" + os.path.join(cli.bundled_configs_dir(), "up3d.py"))


def test_bundled_config_imports_its_siblings_over_another_configs_package(
        tmp_path, monkeypatch, clean_configs_modules):
    """A user's project with its own ``configs`` package: ``configs/synthetic.py`` (absent
    there) is the bundled one, and its ``from configs import default`` the bundled default."""
    (tmp_path / "configs").mkdir()
    (tmp_path / "configs" / "__init__.py").write_text("")
    (tmp_path / "configs" / "default.py").write_text("raise ImportError('the wrong default')")
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    path = cli.resolve_config("configs/synthetic.py")
    cli.use_configs_package(path)
    config = _load_like_config_flags(path).get_config("smoke")
    assert config.train.num_steps == 20
    assert sys.modules["configs"].__path__ == [cli.bundled_configs_dir()]


def test_own_config_importing_configs_works_when_no_configs_is_importable(
        tmp_path, monkeypatch, clean_configs_modules):
    """After ``pip install`` no ``configs`` is importable; a copy of configs/own_json.py
    elsewhere still gets the bundled ``configs.default``."""
    path = tmp_path / "mine.py"
    shutil.copy(os.path.join(ROOT, "configs", "own_json.py"), path)
    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "configs" else find_spec(name, *a))
    for name in [n for n in sys.modules if n == "configs" or n.startswith("configs.")]:
        del sys.modules[name]  # clean_configs_modules puts them back
    cli.use_configs_package(str(path))
    assert _load_like_config_flags(str(path)).get_config().data.source == "json"


def test_get_config_gives_a_bundled_config_with_its_variant_from_any_directory(
        tmp_path, monkeypatch, clean_configs_modules):
    monkeypatch.chdir(tmp_path)  # no configs/ here, as after pip install in a notebook
    for name in [n for n in sys.modules if n == "configs" or n.startswith("configs.")]:
        monkeypatch.delitem(sys.modules, name)
    smoke = cli.get_config("configs/synthetic.py:smoke")
    full = cli.get_config("configs/synthetic.py")
    assert smoke.data.source == full.data.source == "synthetic"
    assert (smoke.train.num_steps, smoke.model.n_fully_connected) == (20, 32)
    assert full.model.n_fully_connected == 256
    with pytest.raises(FileNotFoundError, match="configs/synthetic.py"):
        cli.get_config("configs/no_such_config.py")
    # Locked as on the command line: a typo is an error, not a field nothing reads.
    smoke.train.num_steps = 5
    with pytest.raises(AttributeError, match="num_stepz"):
        smoke.train.num_stepz = 5
    # A notebook's own ``configs`` package is left as it was.
    mine = tmp_path / "mine" / "configs"
    mine.mkdir(parents=True)
    (mine / "__init__.py").write_text("MINE = True\n")
    (mine / "mything.py").write_text("VALUE = 3\n")
    monkeypatch.syspath_prepend(str(tmp_path / "mine"))
    import configs.mything

    cli.get_config("configs/synthetic.py:smoke")
    assert sys.modules["configs"].MINE and sys.modules["configs.mything"] is configs.mything


def test_error_messages_are_one_line():
    assert cli.error_message(KeyError("kp_loc")) == "missing key 'kp_loc'"
    typo = AttributeError(KeyError("'num_step'\nDid you mean \"num_steps\" instead?"))
    assert cli.error_message(typo) == (
        "no config field 'num_step'; Did you mean \"num_steps\" instead?")
    wrapped = flags.IllegalFlagValueError(
        "flag --config=c.py:smok: Error whilst parsing config file:\n\nTraceback (most recent "
        "call last):\n  File \"c.py\", line 1\nValueError: unknown config variant(s) ['smok']\n")
    assert cli.error_message(wrapped) == (
        "flag --config=c.py:smok: ValueError: unknown config variant(s) ['smok']")
    required = flags.IllegalFlagValueError(
        "flag --config=None: Flag --config must have a value other than None.\nflag "
        "--workdir=None: Flag --workdir must have a value other than None.")
    assert cli.error_message(required) == ("--config, --workdir are required (--help shows the "
                                           "flags and an example)")


def test_log_filter_keeps_own_info_and_drops_library_chatter_and_hidden_lines():
    keep = cli._LogFilter(hidden=("step %d:",)).filter

    def record(level, path, msg):
        return logging.LogRecord("absl", level, path, 1, msg, (), None)

    own = os.path.join(os.path.dirname(cli.__file__), "train.py")
    orbax = os.path.join("site-packages", "orbax", "checkpoint", "manager.py")
    assert keep(record(logging.INFO, own, "resumed from the checkpoint at step %d in %s"))
    assert not keep(record(logging.INFO, own, "step %d: %s"))
    assert not keep(record(logging.INFO, orbax, "Saving checkpoint"))
    assert not keep(record(logging.INFO, "jax/_src/xla_bridge.py", "Unable to initialize"))
    assert keep(record(logging.WARNING, orbax, "something is wrong"))


def _pyproject():
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    with open(os.path.join(ROOT, "pyproject.toml"), "rb") as f:
        return tomllib.load(f)


def test_pyproject_ships_configs_inside_the_package_and_the_console_scripts():
    from setuptools import find_packages

    setup = _pyproject()["tool"]["setuptools"]
    assert "configs" not in setup["packages"] and "c3dpo_jax.configs" in setup["packages"]
    assert setup["package-dir"] == {"c3dpo_jax.configs": "configs"}
    assert set(find_packages(ROOT, include=["c3dpo_jax*"])) <= set(setup["packages"])
    for target in _pyproject()["project"]["scripts"].values():
        module, function = target.split(":")
        with open(importlib.util.find_spec(module).origin) as f:
            tree = ast.parse(f.read())
        assert function in {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}
    with open(os.path.join(ROOT, "LICENSE")) as f:
        assert f.readline().strip() == "MIT License" and "the c3dpo_jax authors" in f.read()


def test_main_from_another_directory_reads_the_bundled_config_and_reports_input_errors(
        tmp_path, smoke_subprocess_env):
    """A missing data file fails before training: one line, exit status 2; ``--verbose``
    shows the traceback. Run where no ``configs/`` exists."""
    env = dict(smoke_subprocess_env(), PYTHONPATH=ROOT)
    args = [sys.executable, "-m", "c3dpo_jax.main", "--config=configs/synthetic.py:smoke",
            f"--workdir={tmp_path / 'run'}", "--config.data.train_path=missing.json",
            "--config.data.test_path=missing.json"]
    out = subprocess.run(args, cwd=tmp_path, env=env, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 2, out.stderr[-3000:]
    assert out.stderr == "error: dataset file 'missing.json' does not exist\n"
    assert out.stdout.startswith(f"c3dpo_jax train: {BUNDLED_SYNTHETIC}:smoke -> ")
    verbose = subprocess.run([*args, "--verbose"], cwd=tmp_path, env=env, capture_output=True,
                             text=True, timeout=300)
    assert verbose.returncode != 0 and "Traceback" in verbose.stderr
    assert "config:" in verbose.stderr  # --verbose logs the resolved config
    bad_variant = subprocess.run([*args[:3], "--config=configs/synthetic.py:smok", args[4]],
                                 cwd=tmp_path, env=env, capture_output=True, text=True,
                                 timeout=300)
    assert bad_variant.returncode == 2
    assert bad_variant.stderr.startswith("error: flag --config=") and bad_variant.stderr.endswith(
        "ValueError: unknown config variant(s) ['smok']; known: ('smoke', 'base', 'equiv', "
        "'full', 'paper', 'supervised')\n")
    stray = subprocess.run([*args, "--config.model.canonicalization", "False"], cwd=tmp_path,
                           env=env, capture_output=True, text=True, timeout=300)
    assert stray.returncode == 2
    assert stray.stderr == ("error: unexpected argument(s) 'False': give every value with '=' "
                            "(e.g. --config.model.canonicalization=False)\n")


def _main_refuses(tmp_path, env, *args) -> str:
    """The command's stderr, having refused ``args`` with exit status 2 and made nothing."""
    out = subprocess.run([sys.executable, "-m", "c3dpo_jax.main", f"--workdir={tmp_path / 'run'}",
                          *args], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 2 and not (tmp_path / "run").exists(), out.stderr[-3000:]
    return out.stderr


def test_a_config_override_naming_no_section_names_the_flag_and_the_sections(
        tmp_path, smoke_subprocess_env):
    # config_flags alone: 'missing key "'foo'"'.
    assert _main_refuses(tmp_path, smoke_subprocess_env(), "--config=configs/synthetic.py:smoke",
                         "--config.foo.bar=1") == (
        "error: --config.foo.bar: the config has no section 'foo'; its sections: data, "
        "inference, loss, model, optim, train\n")


def test_a_config_override_without_a_config_asks_for_one(tmp_path, smoke_subprocess_env):
    # absl alone: "Unknown command line flag 'config.model.n_keypoints'".
    assert _main_refuses(tmp_path, smoke_subprocess_env(), "--config.model.n_keypoints=18") == (
        "error: --config.model.n_keypoints sets a field of the config, and no --config=FILE "
        "names one: add it, e.g. --config=configs/own_json.py\n")


def test_what_a_config_override_names_that_is_not_there():
    def problem(*overrides):
        return cli._override_problem(["prog", "--config=configs/synthetic.py:smoke", *overrides])

    assert problem("--config.model.n_keypoints=3", "--config.data.synthetic.seed=1") is None
    assert problem("--config.modl.n_keypoints=3") == (
        "--config.modl.n_keypoints: the config has no section 'modl' (did you mean 'model'?); "
        "its sections: data, inference, loss, model, optim, train")
    assert problem("--config.data.synthetic.n_keypoint=3") == (
        "--config.data.synthetic.n_keypoint: config.data.synthetic has no field 'n_keypoint' "
        "(did you mean 'n_keypoints'?)")
    assert problem("--config.model.n_keypoints.x=3") == (
        "--config.model.n_keypoints.x: config.model.n_keypoints is a value, not a section "
        "with fields")
    # An inference option set in the model section (test_time_*): the line names its field.
    assert problem("--config.model.test_time_refine_iters=0") == (
        "--config.model.test_time_refine_iters: config.model.test_time_refine_iters is now "
        "config.inference.refine_iters")
    assert problem("--config.inference.refine_iters=0") is None


def test_the_results_table_names_what_was_trained():
    from c3dpo_jax import main

    names = {arg: main._method(cli.get_config(arg)) for arg in (
        "configs/own_json.py", "configs/own_json.py:supervised", "configs/synthetic.py:base",
        "configs/synthetic.py:equiv", "configs/h36m.py")}
    assert names == {"configs/own_json.py": "C3DPO",
                     "configs/own_json.py:supervised": "3D-supervised network",
                     "configs/synthetic.py:base": "C3DPO-base",
                     "configs/synthetic.py:equiv": "C3DPO-equiv", "configs/h36m.py": "C3DPO"}


def test_the_config_reference_names_every_field():
    from configs import default

    with open(os.path.join(ROOT, "docs", "config.md")) as f:
        names = set(re.findall(r"`([a-z_]+(?:\.[a-z_*]+)+)`", f.read()))

    def leaves(cfg, prefix=""):
        for key, value in cfg.items():
            if hasattr(value, "items"):
                yield from leaves(value, f"{prefix}{key}.")
            else:
                yield prefix + key

    fields = [f for f in leaves(default.get_config()) if "." in f]
    missing = [f for f in fields if f not in names and f.rsplit(".", 1)[0] + ".*" not in names]
    assert not missing, f"docs/config.md does not list {missing}"


def test_a_ctrl_c_outside_the_training_loop_ends_with_one_line():
    # Loading, compiling, the final evaluation or the pictures: KeyboardInterrupt reaches
    # the command's wrapper, which says so in one line with the shell's status for SIGINT.
    script = ("from absl import flags\nfrom c3dpo_jax import cli\n"
              "verbose = flags.DEFINE_bool('verbose', False, '')\n"
              "def main(argv):\n    raise KeyboardInterrupt\n"
              "cli.run(main, verbose, on_interrupt='nothing was written')\n")
    out = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 130 and out.stderr == "interrupted: nothing was written\n", out
    out = subprocess.run([sys.executable, "-c", script, "--verbose"], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode != 0 and "Traceback" in out.stderr and "KeyboardInterrupt" in out.stderr
    # A Ctrl-C that lands in a callback (here the garbage collector's, as JAX's can be)
    # would be printed as "Exception ignored" and the command would go on; SIGTERM (e.g.
    # `timeout`) ends with the same kind of line and its own status.
    for body, status in (
            ["gc.callbacks.append(lambda *a: signal.raise_signal(signal.SIGINT))",
             "gc.collect()"], 130), (["os.kill(os.getpid(), signal.SIGTERM)", "time.sleep(30)"],
                                     143):
        lines = ["import gc, os, signal, time", "from absl import flags",
                 "from c3dpo_jax import cli", "verbose = flags.DEFINE_bool('verbose', False, '')",
                 "def main(argv):", *(f"    {line}" for line in body), "    print('went on')",
                 "cli.run(main, verbose, on_interrupt='nothing was written')"]
        out = subprocess.run([sys.executable, "-c", "\n".join(lines)], cwd=ROOT,
                             capture_output=True, text=True, timeout=120)
        assert out.returncode == status and out.stdout == "", out
        assert out.stderr == "interrupted: nothing was written\n", out
