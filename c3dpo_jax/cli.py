"""What the package's commands share: bundled configs, quiet logs, one-line user errors.

``c3dpo-train`` (``python -m c3dpo_jax.main``) and ``c3dpo-predict`` (``python -m
c3dpo_jax.predict``) start through ``run``, which

- reads ``--config=configs/NAME.py[:ARGS]`` from the configs shipped with the package
  (``c3dpo_jax/configs`` when installed, the repository's ``configs/`` in a checkout) when
  no such file exists relative to the working directory, so the documented commands work
  from any directory after ``pip install``;
- prints errors in the user's input (files, flag values, config overrides) as one line
  ``error: MESSAGE`` on stderr with exit status 2 instead of a traceback (``--verbose``
  keeps the traceback).

``setup_logging`` drops library INFO chatter and writes log lines above the progress bar.
"""

import ast
import importlib.util
import logging as py_logging
import os
import re
import signal
import sys
from collections.abc import Callable

from absl import app, flags, logging
from tqdm import tqdm

from c3dpo_jax import stops

# What input the user got wrong (json.JSONDecodeError and UnicodeDecodeError are ValueErrors;
# OSError covers missing, unreadable and unwritable files; FloatingPointError is a run whose
# loss diverged, e.g. at too high a learning rate).
USER_ERRORS = (OSError, ValueError, KeyError, FloatingPointError)

# INFO records from other packages are chatter: orbax logs dozens of lines per checkpoint,
# JAX "Unable to initialize backend 'tpu'" on every CPU run, matplotlib its writers.
_PACKAGE_DIR = os.path.dirname(os.path.abspath(__file__)) + os.sep


def bundled_configs_dir() -> str:
    """The configs shipped with the package: ``c3dpo_jax/configs`` in an installed wheel
    (pyproject maps the repository's top-level ``configs/`` there), else the checkout's
    ``configs/`` (an editable install or no install)."""
    package = os.path.dirname(os.path.abspath(__file__))
    installed = os.path.join(package, "configs")
    return installed if os.path.isdir(installed) else os.path.join(os.path.dirname(package),
                                                                   "configs")


def resolve_config(value: str) -> str:
    """A ``--config`` value -> the file for config_flags to load, ``:ARGS`` kept.

    A path that exists relative to the working directory is kept; otherwise
    ``configs/NAME.py`` is the bundled copy. Neither: FileNotFoundError listing the bundled
    configs (config_flags would only fail later, with a longer message); a file that
    defines no ``get_config`` (a helper the configs import): ValueError.
    """
    path, sep, args = value.partition(":")
    if not os.path.exists(path):
        parts = os.path.normpath(path).split(os.sep)
        bundled = os.path.join(bundled_configs_dir(), *parts[1:])
        if not (parts[0] == "configs" and len(parts) > 1 and os.path.isfile(bundled)):
            raise FileNotFoundError(f"config file {path!r} not found; {_bundled_list()}")
        value = bundled + sep + args
    if not _defines_get_config(value.partition(":")[0]):
        raise ValueError(f"{path} defines no get_config(): it is not a config (the configs "
                         f"import it); {_bundled_list()}")
    return value


def _defines_get_config(path: str) -> bool:
    """Whether the Python file ``path`` defines, assigns or imports a top-level
    ``get_config`` (a file that does not parse is left to the loader to report)."""
    try:
        with open(path) as f:
            tree = ast.parse(f.read())
    except (OSError, SyntaxError, ValueError):
        return True
    for node in tree.body:
        if isinstance(node, ast.FunctionDef) and node.name == "get_config":
            return True
        if isinstance(node, ast.Assign) and any(
                isinstance(t, ast.Name) and t.id == "get_config" for t in node.targets):
            return True
        if isinstance(node, (ast.Import, ast.ImportFrom)) and any(
                (a.asname or a.name.rpartition(".")[2]) == "get_config" for a in node.names):
            return True
    return False


def _bundled_list() -> str:
    names = sorted(n for n in os.listdir(bundled_configs_dir()) if n.endswith(".py")
                   and not n.startswith("_")
                   and _defines_get_config(os.path.join(bundled_configs_dir(), n)))
    return "the bundled configs are " + ", ".join(f"configs/{n}" for n in names)


def use_configs_package(config_file: str) -> None:
    """Makes ``configs`` (the config files import each other as ``from configs import
    default``) the package for ``config_file``.

    config_flags executes the file by path, so that import needs ``configs`` in
    ``sys.modules`` or on ``sys.path``: the file's own ``configs`` package when it lives in
    one (the repository's, or the bundled copy even when the working directory holds
    another ``configs``), else the bundled configs when no ``configs`` is importable (a
    config of the user's own after ``pip install``).
    """
    directory = os.path.dirname(os.path.abspath(config_file))
    init = os.path.join(directory, "__init__.py")
    if os.path.basename(directory) != "configs" or not os.path.isfile(init):
        if "configs" in sys.modules or importlib.util.find_spec("configs") is not None:
            return
        directory = bundled_configs_dir()
        init = os.path.join(directory, "__init__.py")
    for name in [n for n in sys.modules if n == "configs" or n.startswith("configs.")]:
        del sys.modules[name]  # submodules of another ``configs`` would shadow these files
    spec = importlib.util.spec_from_file_location("configs", init,
                                                  submodule_search_locations=[directory])
    module = importlib.util.module_from_spec(spec)
    sys.modules["configs"] = module
    spec.loader.exec_module(module)


def get_config(spec: str):
    """The ConfigDict that ``--config=SPEC`` gives, for notebooks and scripts, from any
    directory: ``SPEC`` is ``configs/NAME.py[:ARGS]`` (the bundled copy unless the path
    exists relative to the working directory) or a config file of one's own.

    Example: ``get_config("configs/synthetic.py:smoke")``. The config is locked, as the
    command line's: a field that does not exist (a typo) is an error, not a new field that
    nothing reads.
    """
    path, _, arg = resolve_config(spec).partition(":")
    # ``sys.modules``' ``configs`` entries are put back as they were: the config files
    # import the package's ``configs``, and a notebook may have its own (a common name).
    theirs = {n: m for n, m in sys.modules.items() if n == "configs" or n.startswith("configs.")}
    try:
        use_configs_package(path)
        name = os.path.splitext(os.path.basename(path))[0]
        module_spec = importlib.util.spec_from_file_location(f"_c3dpo_config_{name}", path)
        module = importlib.util.module_from_spec(module_spec)
        module_spec.loader.exec_module(module)
        config = module.get_config(arg or None)
    finally:
        for n in [n for n in sys.modules if n == "configs" or n.startswith("configs.")]:
            del sys.modules[n]
        sys.modules.update(theirs)
    config.lock()
    return config


def _resolve_config_argv(argv: list[str]) -> list[str]:
    """``argv`` with its ``--config`` value (``=`` or next argument) resolved."""
    argv = list(argv)
    for i, arg in enumerate(argv):
        name, eq, value = arg.partition("=")
        if name not in ("--config", "-config") or not (eq or i + 1 < len(argv)):
            continue
        j, value = (i, value) if eq else (i + 1, argv[i + 1])
        value = resolve_config(value)
        argv[j] = f"{name}={value}" if eq else value
        use_configs_package(value.partition(":")[0])
    return argv


def error_message(err: BaseException) -> str:
    """``err`` as one line: a traceback that config_flags puts into its message is cut to
    its last line; a missing key or config field is named as such."""
    text = str(err).strip()
    if "Traceback (most recent call last)" in text:
        lines = [line.strip() for line in text.splitlines() if line.strip()]
        head = lines[0].replace(" Error whilst parsing config file:", "")
        return f"{head} {lines[-1]}"
    if isinstance(err, AttributeError) and err.args and isinstance(err.args[0], KeyError):
        # ml_collections, for an override naming no field: AttributeError(KeyError(message))
        return "no config field " + "; ".join(str(err.args[0].args[0]).splitlines())
    if isinstance(err, KeyError):
        return f"missing key {text}"
    missing = re.findall(r"Flag (--\w+) must have a value other than None", text)
    if missing:  # absl names each required flag not given on a line of its own
        return (f"{', '.join(missing)} {'is' if len(missing) == 1 else 'are'} required "
                "(--help shows the flags and an example)")
    return text


def fail(err: BaseException) -> None:
    """Exits as every command does on a user error: ``error: MESSAGE`` on stderr, status 2."""
    print(f"error: {error_message(err)}", file=sys.stderr)
    sys.exit(2)


def _config_flag(arg: str) -> str:
    """``--config.a.b`` of an argument ``--config.a.b=value`` ('' for other arguments)."""
    name = arg.partition("=")[0]
    return name if name.startswith(("--config.", "-config.")) else ""


def _overrides_without_config(argv: list[str]) -> None:
    """``--config.a.b=v`` with no ``--config=FILE`` to override (absl would call the flag
    unknown): a ValueError that says so."""
    overrides = [a for a in argv[1:] if _config_flag(a)]
    if (overrides and "config" in flags.FLAGS
            and not any(a.partition("=")[0] in ("--config", "-config") for a in argv[1:])):
        raise ValueError(f"{_config_flag(overrides[0])} sets a field of the config, and no "
                         "--config=FILE names one: add it, e.g. --config=configs/own_json.py")


def _override_problem(argv: list[str]) -> str | None:
    """The first ``--config.a.b=v`` of ``argv`` (``--config`` resolved) whose path names no
    field of the config, said with the flag and the sections there are (config_flags
    raises a bare KeyError for a missing section); None when they all name one."""
    import difflib

    from ml_collections import ConfigDict

    from c3dpo_jax.model import MOVED_TO_INFERENCE

    spec = next((a.partition("=")[2] for a in argv if a.startswith(("--config=", "-config="))),
                None)
    if not spec:
        return None
    try:
        config = get_config(spec)
    except Exception:  # noqa: BLE001 (a config that fails to load: its own error is shown)
        return None
    for flag in filter(None, map(_config_flag, argv)):
        path = flag.split(".")[1:]
        node, where = config, "the config"
        for depth, key in enumerate(path):
            if not isinstance(node, ConfigDict):
                return f"{flag}: {where} is a value, not a section with fields"
            if key not in node:
                if depth == 1 and path[0] == "model" and key in MOVED_TO_INFERENCE:
                    return (f"{flag}: config.model.{key} is now "
                            f"config.inference.{MOVED_TO_INFERENCE[key]}")
                close = difflib.get_close_matches(key, list(node), n=1)
                sections = sorted(k for k in node if isinstance(node[k], ConfigDict))
                what = "section" if depth < len(path) - 1 else "field"
                return (f"{flag}: {where} has no {what} {key!r}"
                        + (f" (did you mean {close[0]!r}?)" if close else "")
                        + (f"; its sections: {', '.join(sections)}" if sections else ""))
            node, where = node[key], "config." + ".".join(path[:depth + 1])
    return None


def _parse_flags(argv: list[str]) -> list[str]:
    """absl's flag parsing, with ``--config`` resolved and one-line errors (exit status 2)."""
    resolved = argv
    try:
        _overrides_without_config(argv)
        resolved = _resolve_config_argv(argv)
        return flags.FLAGS(resolved)
    except (flags.Error, AttributeError, *USER_ERRORS) as err:
        if any(a.startswith("--verbose") for a in argv):
            raise
        problem = (_override_problem(resolved) if isinstance(err, (KeyError, AttributeError))
                   else None)
        fail(ValueError(problem) if problem else err)


def is_verbose(verbose: flags.FlagHolder | None) -> bool:
    """``--verbose`` (when the command has it), or absl's ``-v 1`` (debug logging)."""
    return (verbose is not None and verbose.value) or logging.get_verbosity() >= logging.DEBUG


def run(main: Callable[[list[str]], None], verbose: flags.FlagHolder | None = None,
        on_interrupt: str = "stopped", positional: bool = False) -> None:
    """``app.run(main)`` as the package's commands (and the repository's experiments) run
    (module docstring): an error in the input, including ``app.UsageError``, is one line; a
    Ctrl-C or SIGTERM ends with one line and exit status 130 / 143: the training loop's
    ``stops.Interrupted`` (checkpointed), else ``interrupted: ON_INTERRUPT``
    (``stops.end_at_once``; ``--verbose`` or ``-v 1``: Python's own handling, a
    KeyboardInterrupt's traceback).
    Arguments that are not flags are refused unless ``positional`` (``main`` reads them)."""
    # --helpshort lists the flags of the file in argv[0]: a console script defines none; and
    # --help starts with __main__'s docstring, which a console script's wrapper lacks.
    for flag in flags.FLAGS.get_key_flags_for_module(main.__module__):
        flags.FLAGS.register_key_flag_for_module(sys.argv[0], flag)
    script = sys.modules.get("__main__")
    if script is not None and not script.__doc__:
        script.__doc__ = sys.modules[main.__module__].__doc__

    def guarded(argv):
        if not is_verbose(verbose):
            stops.end_at_once(on_interrupt)
        try:
            if len(argv) > 1 and not positional:  # "--config.x False": absl leaves "False"
                raise ValueError(f"unexpected argument(s) {' '.join(argv[1:])!r}: give every "
                                 "value with '=' (e.g. --config.model.canonicalization=False)")
            main(argv)
        except stops.Interrupted as err:  # the loop's stop: checkpointed, resumable
            print(str(err), file=sys.stderr)
            sys.exit(err.exit_code)
        except (app.UsageError, *USER_ERRORS) as err:
            if is_verbose(verbose):
                raise
            fail(err)
        except KeyboardInterrupt:
            if is_verbose(verbose):
                raise
            print(f"interrupted: {on_interrupt}", file=sys.stderr, flush=True)
            sys.exit(128 + signal.SIGINT)

    app.run(guarded, flags_parser=_parse_flags)


class _LogFilter(py_logging.Filter):
    """Keeps warnings and errors, and INFO records of c3dpo_jax's own code whose format
    string starts with none of ``hidden``."""

    def __init__(self, hidden: tuple[str, ...]):
        super().__init__()
        self.hidden = hidden

    def filter(self, record):
        if record.levelno >= py_logging.WARNING:
            return True
        return (os.path.abspath(record.pathname).startswith(_PACKAGE_DIR)
                and not str(record.msg).startswith(self.hidden))


class _AboveTheBar:
    """The log handler's stream: ``tqdm.write`` lifts the progress bar, writes the line and
    redraws the bar below it, so that log lines never cut through the bar."""

    def write(self, text: str) -> None:
        tqdm.write(text, file=sys.stderr, end="")

    def flush(self) -> None:
        sys.stderr.flush()

    def close(self) -> None:
        """The handler closes its stream at exit; stderr stays open."""


class _PlainFormatter(py_logging.Formatter):
    """A command's log lines as plain text: the message, ``warning: `` before a warning's
    (absl's ``I1128 00:04:58.495953 1399... train.py:299]`` prefix is for log files)."""

    def format(self, record: py_logging.LogRecord) -> str:
        text = record.getMessage()
        if record.levelno >= py_logging.WARNING:
            text = f"{py_logging.getLevelName(record.levelno).lower()}: {text}"
        if record.exc_info:
            text += "\n" + self.formatException(record.exc_info)
        return text


def setup_logging(hidden: tuple[str, ...] = ()) -> None:
    """Quiet logs for a command: INFO only from c3dpo_jax (not orbax, JAX or matplotlib)
    and not when its format string starts with one of ``hidden``; plain lines
    (``_PlainFormatter``), every one above the progress bar."""
    handler = logging.get_absl_handler()
    handler.addFilter(_LogFilter(hidden))
    handler.setFormatter(_PlainFormatter())
    handler.python_handler.setStream(_AboveTheBar())
