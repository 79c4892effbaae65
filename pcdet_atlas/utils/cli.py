"""What every tool does with a user's mistake: one line on stderr and exit status 2.

A tool ends with ``run_tool(main)`` and documents the flag with :func:`add_debug_flag`. A *user
error* is an exception the project raises on purpose about its input (any class defined in
``pcdet_atlas``, such as ``ConfigError`` or ``WaymoFormatError``) or a ``ValueError`` /
``OSError`` (a bad value, a missing or unreadable file): it prints ``<tool>: error: <message>``
and exits with status 2, as argparse does for a bad flag. ``--debug`` anywhere on the command line
shows the traceback instead. A tool's own ``raise SystemExit("<message>")`` is a user error too
(the same line and status; ``--debug`` prints the traceback before it). Any other exception is a
bug and keeps its traceback.

A tool refuses to run on the package of another tree (:func:`check_package_tree`): with two
clones, an editable install of one would otherwise serve the other's tools its code, configs and
checkpoints without a word.

``--plugin MODULE`` (:func:`add_plugin_flag`, repeatable) imports a user's module before the
tool's work: a module that registers a detector, a model stage, an attack family (any registry
of :data:`pcdet_atlas.registry.REGISTRIES`) with the project's decorators, so the configs can
name it. :func:`import_plugins` is the one place plugins are imported.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import os
import sys
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path

from pcdet_atlas.registry import REGISTRIES

__all__ = [
    "DEBUG_FLAG",
    "PluginError",
    "add_debug_flag",
    "add_plugin_flag",
    "add_set_flag",
    "check_package_tree",
    "import_plugins",
    "is_user_error",
    "run_tool",
]

DEBUG_FLAG = "--debug"
USER_ERROR_EXIT = 2


def add_debug_flag(parser: argparse.ArgumentParser) -> None:
    """List ``--debug`` in the tool's ``--help`` (:func:`run_tool` reads and removes it)."""
    parser.add_argument(DEBUG_FLAG, action="store_true", help="show the full traceback of an error")


def add_set_flag(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup,
    help: str = "KEY VALUE pairs overriding the config (last on the command line)",
    default: list | None = None,
) -> None:
    """``--set KEY VALUE ...`` (``args.set_cfgs``): config overrides, the rest of the line."""
    parser.add_argument(
        "--set", dest="set_cfgs", nargs=argparse.REMAINDER, default=default, help=help
    )


class PluginError(ValueError):
    """A ``--plugin`` module that cannot be found or registers nothing."""


def add_plugin_flag(parser: argparse.ArgumentParser) -> None:
    """``--plugin MODULE`` (repeatable; ``args.plugin``, a list): the tool calls
    :func:`import_plugins` with it before its work."""
    parser.add_argument(
        "--plugin", action="append", default=[], metavar="MODULE",
        help="import MODULE first (a dotted module name on the Python path, or a .py file): a "
        "module registering a detector, model stage or attack family (repeatable)",
    )  # fmt: skip


def _import_file(path: Path):
    """Import the ``.py`` file ``path`` as the module named by its stem (once per process)."""
    name = path.stem
    loaded = sys.modules.get(name)
    if loaded is not None:
        if Path(getattr(loaded, "__file__", "") or "").resolve() != path.resolve():
            raise PluginError(
                f"--plugin {path}: a module named {name!r} is imported already (from "
                f"{getattr(loaded, '__file__', None)}); rename the file"
            )
        return loaded
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except BaseException:
        del sys.modules[name]  # a failed import leaves nothing half-registered behind by name
        raise
    return module


def import_plugins(modules: Sequence[str]) -> dict[str, dict[str, list[str]]]:
    """Import each plugin module (a dotted name importable on ``sys.path``, or the path of a
    ``.py`` file) and return what each registered: ``{module: {registry kind: [names]}}``.

    A module imported before (an earlier tool in the same process) is not imported again and
    counts as registering nothing new. Errors inside a plugin (including a name it registers
    twice, :class:`~pcdet_atlas.registry.RegistryError`) propagate as they are.

    Raises:
        PluginError: a module that is not there, or whose first import registers nothing.
    """
    added: dict[str, dict[str, list[str]]] = {}
    for spec in modules:
        before = {kind: registry.registered_now() for kind, registry in REGISTRIES.items()}
        is_file = spec.endswith(".py")
        name = Path(spec).stem if is_file else spec
        first_import = name not in sys.modules
        if is_file:
            if not Path(spec).is_file():
                raise PluginError(f"--plugin {spec}: no such file")
            _import_file(Path(spec))
        else:
            try:
                importlib.import_module(spec)
            except ModuleNotFoundError as err:
                if err.name is None or not (spec == err.name or spec.startswith(f"{err.name}.")):
                    raise  # the plugin imports something that is missing: its own error
                raise PluginError(
                    f"--plugin {spec}: no module named {err.name!r} on the Python path (pass "
                    "a dotted module name importable from here, or the path of a .py file)"
                ) from None
        added[spec] = {kind: sorted(registry.registered_now() - before[kind])
                       for kind, registry in REGISTRIES.items()
                       if registry.registered_now() - before[kind]}  # fmt: skip
        if first_import and not added[spec]:
            raise PluginError(
                f"--plugin {spec}: registered nothing in the {', '.join(REGISTRIES)} registries "
                "(decorate its classes with e.g. @DETECTORS.register())"
            )
    return added


def is_user_error(err: BaseException) -> bool:
    """Whether ``err`` is about the user's input (module docstring), not a bug."""
    if isinstance(err, (ValueError, OSError)):
        return True
    return any(cls.__module__.startswith("pcdet_atlas") for cls in type(err).__mro__)


class OtherTreeError(RuntimeError):
    """The imported ``pcdet_atlas`` is not the one beside the running tool."""


# A benchmark's --baseline_src child runs this checkout's script on purpose with the package of
# another source tree; it names that tree in this variable, and only that tree is then accepted.
BASELINE_TREE_ENV = "PCDET_ATLAS_BASELINE_TREE"


def baseline_tree_env(src: str | Path) -> dict[str, str]:
    """The environment of a benchmark's child that imports ``pcdet_atlas`` from ``src``."""
    src = Path(src).resolve()
    repo = Path(__file__).resolve().parent.parent.parent
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(src), str(repo)]),
                **{BASELINE_TREE_ENV: str(src)})  # fmt: skip


def check_package_tree(tool_file: str | Path) -> None:
    """Raise :class:`OtherTreeError` when ``tool_file`` (a ``tools/*.py`` or ``tools/*/*.py`` of
    a checkout) runs with the ``pcdet_atlas`` package of another checkout, unless that package's
    tree is the one named in ``$PCDET_ATLAS_BASELINE_TREE`` (:func:`baseline_tree_env`)."""
    tool_path = Path(tool_file).resolve()
    tools = next((p for p in tool_path.parents if p.name == "tools"), tool_path.parent)
    tool_root = tools.parent
    package_root = Path(__file__).resolve().parent.parent.parent  # .../pcdet_atlas/utils/cli.py
    baseline = os.environ.get(BASELINE_TREE_ENV)
    if baseline and Path(baseline).resolve() == package_root:
        return
    if (tool_root / "pcdet_atlas").is_dir() and tool_root != package_root:
        raise OtherTreeError(
            f"{Path(tool_file).name} of {tool_root} imports pcdet_atlas from {package_root}: "
            f"run `pip install -e .` in {tool_root} (or put it first on PYTHONPATH)"
        )


def run_tool(main: Callable[[], object], argv: list[str] | None = None) -> None:
    """Run a tool's ``main()`` with ``sys.argv`` (or ``argv``) minus ``--debug``; a user error
    becomes one line on stderr and exit status 2 unless ``--debug`` was given."""
    args = list(sys.argv[1:] if argv is None else argv)
    debug = DEBUG_FLAG in args
    sys.argv = [sys.argv[0], *(a for a in args if a != DEBUG_FLAG)]
    tool = Path(sys.argv[0]).name
    try:
        check_package_tree(sys.argv[0])
        main()
    except SystemExit as err:  # raise SystemExit("message"): a user error stated by the tool
        if not isinstance(err.code, str):
            raise  # an exit status (argparse's 2, a tool's own)
        if debug:
            traceback.print_exc()
        _stop(tool, err.code)
    except Exception as err:  # noqa: BLE001 - sorted into user errors and bugs below
        if debug or not is_user_error(err):
            raise
        _stop(tool, str(err) or type(err).__name__, f" ({DEBUG_FLAG} shows the traceback)")


def _stop(tool: str, message: str, hint: str = "") -> None:
    """Print a user error as one line, ``<tool>: error: <message><hint>``, and exit with 2."""
    print(f"{tool}: error: {' '.join(message.split())}{hint}", file=sys.stderr)
    sys.exit(USER_ERROR_EXIT)


class RenamedFlag(argparse.Action):
    """A flag that also answers to its old spelling for one release, with a warning on stderr.

    ``parser.add_argument("--out_dir", "--out", action=RenamedFlag, old=("--out",), ...)``:
    ``--out DIR`` still sets ``out_dir`` and prints ``<tool>: warning: --out is deprecated ...;
    use --out_dir``. Any other keyword is argparse's, as for a plain stored flag.
    """

    def __init__(self, option_strings, dest, old=(), **kwargs):
        unknown = [flag for flag in old if flag not in option_strings]
        if unknown:
            raise ValueError(f"RenamedFlag: old spellings {unknown} are not among {option_strings}")
        self.old = tuple(old)
        self.new = next(s for s in option_strings if s not in self.old)
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        if option_string in self.old:
            print(
                f"{parser.prog}: warning: {option_string} is deprecated and goes in the next "
                f"release; use {self.new}",
                file=sys.stderr,
            )
        setattr(namespace, self.dest, values)
