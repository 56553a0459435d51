"""Shared plumbing for CLI commands: how every command fails, option checks, progress bars.

The promise of the README: bad input gives exactly one line on stderr, starting with ``error:``,
that names the file or option, and exit code 2; Ctrl-C, SIGTERM and SIGHUP give one line and exit
code 130. The pieces:

- :class:`LabGroup`, the click group of the app (``typer.Typer(cls=LabGroup)``): runs the command
  line and turns typer's own rejections into one line (``error: --method: 'foo' is not one of ls,
  l1, sbl, rpca``), makes SIGTERM/SIGHUP unwind like Ctrl-C, refuses NaN/infinity in every float
  parameter of every command and gives commands without :func:`lab_command` its handling
  (:func:`guard_commands`), and holds log warnings until the command
  succeeds (:data:`HELD`).
- :func:`lab_command`, the decorator of every command: :class:`PsLabError` → its message;
  ``OSError`` → the file and the reason; ``MemoryError`` → one line; any other exception is a bug →
  one line naming the log file with the traceback (``-vv`` prints it).
- Parsers for option values given as text (:func:`parse_numbers`), validating where they enter.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
import os
import re
import signal
import sys
import tempfile
import time
import traceback
from collections.abc import Callable, Collection, Iterator, Mapping
from contextlib import contextmanager
from enum import Enum
from pathlib import Path
from typing import Any, TypeVar

import typer
from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from typer.core import TyperGroup

from ps_lab.errors import PsLabError

try:  # typer >= 0.25 carries its own copy of click
    from typer._click import core as _click_core
    from typer._click import exceptions as _click_exc
    from typer.exceptions import Abort, Exit
except ImportError:  # pragma: no cover - older typer on top of click
    from click import core as _click_core
    from click import exceptions as _click_exc
    from click.exceptions import Abort, Exit

F = TypeVar("F", bound=Callable[..., Any])
D = TypeVar("D")
log = logging.getLogger("ps_lab")

EXIT_USER_ERROR = 2
EXIT_INTERRUPTED = 130

#: Settings of every ``typer.Typer`` of the app (``typer.Typer(..., **HELP_SETTINGS)``): ``-h`` as
#: well as ``--help`` (click passes it down to every command), and click's plain help layout,
#: which wraps help text but never cuts an option name (typer's rich tables do at 80 columns)
#: and prints help text as written (rich markup would eat a ``[default: ...]``).
HELP_SETTINGS: dict[str, Any] = {
    "context_settings": {"help_option_names": ["-h", "--help"]},
    "rich_markup_mode": None,
}


_reported: list[str] = []  # error lines printed by this process


def fail(message: str, code: int = EXIT_USER_ERROR) -> typer.Exit:
    """Print ``message`` as one red line on stderr and return the ``typer.Exit`` to raise."""
    typer.secho(f"error: {message}", fg=typer.colors.RED, err=True)
    _reported.append(message)
    return typer.Exit(code)


def _say(message: str, code: int) -> int:
    fail(message, code)
    return code


def lab_command(func: F) -> F:
    """Wrap a command so that every failure is one red line: exit 2, or 130 when interrupted.

    :class:`PsLabError` prints its message; ``OSError`` the file and the reason; Ctrl-C, SIGTERM
    and SIGHUP "interrupted" (outputs are staged, so nothing partial is left); any other exception
    is a bug: one line naming the log file that holds the traceback (``-vv`` prints it).
    """

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return func(*args, **kwargs)
        except PsLabError as exc:
            raise fail(str(exc)) from None
        except KeyboardInterrupt as exc:
            # A command that kept something says what (``exc.outcome``, e.g. ps-lab batch).
            outcome = getattr(exc, "outcome", None) or "no output written"
            raise fail(f"{interrupted_line(exc)}; {outcome}", EXIT_INTERRUPTED) from None
        except (Exit, Abort, _click_exc.ClickException):
            raise
        except MemoryError:
            raise fail("out of memory (try a smaller --memory-budget, or free memory)") from None
        except OSError as exc:
            raise fail(os_error_line(exc)) from None
        except Exception as exc:  # noqa: BLE001 - a bug: one line, traceback in the log
            raise fail(bug_line(exc)) from None

    return wrapper  # type: ignore[return-value]


def choices(name: str, values: str, doc: str) -> type[Enum]:
    """The ``str`` Enum of a choice option: ``choices("Lights", "auto near directional", ...)``.

    One line of values where a class would write each name twice; typer offers the values
    (space-separated in ``values``), and member names are the values with ``-`` as ``_``
    (``flat-field`` is ``.flat_field``). ``doc`` becomes the Enum's docstring.
    """
    members = [(value.replace("-", "_"), value) for value in values.split()]
    choice = Enum(name, members, type=str, module=sys._getframe(1).f_globals["__name__"])
    choice.__doc__ = doc
    return choice


def from_params(
    cls: type[D], params: Mapping[str, Any], *, leave: Collection[str] = (), **given: Any
) -> D:
    """The settings dataclass ``cls`` of a command's parameters (``locals()`` on entry).

    The command's signature is the one table: every parameter named as a field of ``cls`` sets
    it, a choice (Enum) by its value; ``given`` sets fields whose value the command converts
    (or whose option has another name); ``leave`` names parameters the command uses otherwise.
    """
    fields = {field.name for field in dataclasses.fields(cls)} - set(leave)
    values = {
        name: value.value if isinstance(value, Enum) else value
        for name, value in params.items()
        if name in fields
    }
    return cls(**{**values, **given})


def parse_numbers(
    text: str | None,
    option: str,
    names: str,
    *,
    positive: tuple[str, ...] = (),
) -> tuple[float, ...] | None:
    """Parse ``"1,2,3"`` given to ``option`` as finite numbers named ``names`` (``"CX,CY,R"``).

    Raises
    ------
    UsageError
        Wrong count, not numbers, not finite, or a name in ``positive`` that is not > 0; the
        message names the option (one ``error:`` line).

    """
    if text is None:
        return None
    labels = names.split(",")
    try:
        values = tuple(float(p.strip()) for p in text.split(","))
    except ValueError:
        values = ()
    if len(values) != len(labels):
        raise _click_exc.UsageError(
            f"{option} expects {names} (comma-separated numbers), got {text!r}"
        )
    for label, value in zip(labels, values, strict=True):
        if not math.isfinite(value):
            raise _click_exc.UsageError(f"{option}: {label} must be a finite number, got {text!r}")
        if label in positive and value <= 0:
            raise _click_exc.UsageError(f"{option}: {label} must be positive, got {text!r}")
    return values


def positive(value: float | None, option: str) -> None:
    """Refuse a given ``value`` of ``option`` that is not > 0 (one ``error:`` line)."""
    if value is not None and not value > 0:
        raise _click_exc.UsageError(f"{option}: must be positive, got {value!r}")


@contextmanager
def naming_folder(folder: Path, unless: str | None = None) -> Iterator[None]:
    """Prefix ``folder`` to a :class:`PsLabError` whose message names no file of it.

    A message that starts with ``unless`` (another file at fault, such as an outline frame given
    by the user) is left as it is.
    """
    try:
        yield
    except PsLabError as exc:
        if str(folder) in str(exc) or (unless is not None and str(exc).startswith(unless)):
            raise
        try:
            renamed = type(exc)(f"{folder}: {exc}")
        except TypeError:
            renamed = PsLabError(f"{folder}: {exc}")
        raise renamed from None


@contextmanager
def progress_bar(
    total: int, description: str, *, enabled: bool = True
) -> Iterator[Callable[..., None]]:
    """Show a progress bar with an ETA; yield ``advance(n=1, description=None)``.

    The bar goes to stderr, and only when stderr is a terminal: on a pipe or in a log file a
    failed command stays one error line.
    """
    if not enabled or not sys.stderr.isatty():
        yield lambda n=1, description=None: None
        return
    columns = (
        TextColumn("[progress.description]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TextColumn("eta"),
        TimeRemainingColumn(),
    )
    with Progress(*columns, console=Console(stderr=True), transient=False) as progress:
        task = progress.add_task(description, total=total)

        def advance(n: int = 1, description: str | None = None) -> None:
            if description is not None:
                progress.update(task, description=description)
            progress.advance(task, n)

        yield advance


_FORWARDED_SIGNALS = ("SIGTERM", "SIGHUP")


class Interrupted(KeyboardInterrupt):
    """SIGTERM or SIGHUP, raised like Ctrl-C so that every ``finally`` and staging cleanup runs."""


def _raise_interrupted(signum: int, frame: object) -> None:
    raise Interrupted(signal.Signals(signum).name)


def install_signal_handlers() -> dict[int, Any]:
    """Make SIGTERM and SIGHUP unwind like Ctrl-C; return the previous handlers.

    Only signals left at their default action are taken (an ignored SIGHUP under ``nohup`` stays
    ignored); nothing happens outside the main thread.
    """
    previous: dict[int, Any] = {}
    for name in _FORWARDED_SIGNALS:
        sig = getattr(signal, name, None)
        if sig is None:
            continue
        try:
            if signal.getsignal(sig) is signal.SIG_DFL:
                previous[sig] = signal.signal(sig, _raise_interrupted)
        except ValueError:  # not the main thread
            break
    return previous


def restore_signal_handlers(previous: dict[int, Any]) -> None:
    """Put back what :func:`install_signal_handlers` replaced."""
    for sig, handler in previous.items():
        signal.signal(sig, handler)


def interrupted_line(exc: BaseException) -> str:
    """``interrupted (SIGTERM)`` or ``interrupted (Ctrl-C)``."""
    name = exc.args[0] if exc.args and str(exc.args[0]).startswith("SIG") else "Ctrl-C"
    return f"interrupted ({name})"


# --- floats: finite everywhere -----------------------------------------------------------------


def _non_finite(value: Any) -> bool:
    if isinstance(value, float):
        return not math.isfinite(value)
    if isinstance(value, (list, tuple)):
        return any(_non_finite(v) for v in value)
    return False


def guard_commands(command: _click_core.Command) -> None:
    """Give every command under ``command`` the checks and failure handling of the app.

    Each leaf command's ``invoke`` refuses NaN and infinity in any float parameter (after typer
    has converted the values, before the command body: an option added later gets the check
    without declaring anything; the refusal names the option), then runs the command under
    :func:`lab_command`'s handling, so a command that forgot the decorator still fails in one line.
    """
    subcommands = getattr(command, "commands", None)
    if subcommands is not None:
        for sub in subcommands.values():
            guard_commands(sub)
        return
    if getattr(command, "_lab_guarded", False):
        return
    original = lab_command(command.invoke)

    def invoke(ctx: _click_core.Context) -> Any:
        for param in ctx.command.params:
            value = ctx.params.get(param.name)
            if _non_finite(value):
                raise _click_exc.BadParameter(
                    f"{value!r} is not a finite number", ctx=ctx, param=param
                )
        return original(ctx)

    command.invoke = invoke  # type: ignore[method-assign]
    command._lab_guarded = True  # type: ignore[attr-defined]


# --- usage errors as one line ------------------------------------------------------------------


def param_label(param: Any) -> str:
    """``--method`` for an option, ``DATASET`` for an argument."""
    if param is None:
        return ""
    if getattr(param, "param_type_name", "") == "argument":
        return str(param.name or "").upper()
    opts = list(getattr(param, "opts", None) or [])
    longs = [o for o in opts if o.startswith("--")]
    return (longs or opts or [f"--{param.name}"])[0]


#: The app's own options, which go before the command (``ps-lab -v reconstruct ...``).
_ROOT_OPTION = re.compile(r"-v+|--verbose|--version")


def usage_line(exc: _click_exc.ClickException) -> str:
    """One line for a rejection by click/typer: ``--method: 'foo' is not one of ls, l1``."""
    if isinstance(exc, _click_exc.NoSuchOption):
        line = f"{exc.option_name}: no such option"
        if _ROOT_OPTION.fullmatch(exc.option_name) and exc.ctx is not None and exc.ctx.parent:
            # `ps-lab reconstruct DATA -v`: an option of the app itself, given after the command.
            root = exc.ctx.find_root().info_name or "ps-lab"
            command = exc.ctx.command_path[len(root) :].strip()
            if exc.option_name == "--version":
                line += f" of {command}: it is the app's ({root} --version)"
            else:
                line += f" of {command}: -v/-vv go before the command ({root} -v {command} ...)"
        elif exc.possibilities:
            line += f" (did you mean {', '.join(sorted(exc.possibilities))}?)"
        return line
    if isinstance(exc, _click_exc.MissingParameter):
        what = getattr(exc.param, "param_type_name", "option")
        return f"{param_label(exc.param)}: missing (a required {what})"
    message = exc.message.strip()
    message = re.sub(r"^Value error, ", "", message).rstrip(".")
    choice = re.fullmatch(r"(.*) is not one of (.*)", message)
    if choice:
        message = f"{choice[1]} is not one of {choice[2].replace(chr(39), '')}"
    if re.match(r"[A-Z][a-z]", message):
        message = message[:1].lower() + message[1:]
    if isinstance(exc, _click_exc.BadParameter) and exc.param is not None:
        return f"{param_label(exc.param)}: {message}"
    if isinstance(exc, _click_exc.BadParameter) and exc.param_hint:
        return f"{exc.param_hint}: {message}"
    message = re.sub(r"\. Did you mean (.*)\?$", r" (did you mean \1?)", message)
    message = re.sub(r"^No such command '(.*)'", r"no such command '\1'", message)
    message = re.sub(
        r"^Got unexpected extra arguments? \((.*)\)", r"unexpected argument: \1", message
    )
    return message[:1].lower() + message[1:]


# --- warnings held until success ----------------------------------------------------------------


class HeldWarnings(logging.Handler):
    """Hold WARNING+ records; :meth:`print_held` prints them as ``warning:`` lines.

    :meth:`discard` forgets them: a failed command prints its error line only.
    """

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)

    def print_held(self) -> None:
        for record in self.records:
            typer.secho(f"warning: {record.getMessage()}", fg=typer.colors.YELLOW, err=True)
        self.records.clear()

    def discard(self) -> None:
        self.records.clear()


HELD = HeldWarnings()


_LIVE: list[logging.Handler] = []  # the handler -v/-vv added last


def configure_logging(verbose: int) -> None:
    """Default: warnings held (:data:`HELD`); ``-v`` info, ``-vv`` debug, printed as they come.

    Python warnings (``warnings.warn``) go to the log too. Handlers that others attached to the
    root logger (pytest's, an application's) are left alone.
    """
    root = logging.getLogger()
    for handler in [HELD, *_LIVE]:
        root.removeHandler(handler)
    _LIVE.clear()
    HELD.discard()
    logging.captureWarnings(True)
    if verbose == 0:
        root.setLevel(logging.WARNING)
        root.addHandler(HELD)
    else:
        live = logging.StreamHandler(sys.stderr)  # the stderr of this run (CliRunner swaps it)
        live.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
        _LIVE.append(live)
        root.setLevel(logging.INFO if verbose == 1 else logging.DEBUG)
        root.addHandler(live)


# --- bugs ---------------------------------------------------------------------------------------


def log_folder() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "ps-lab"


def bug_line(exc: BaseException) -> str:
    """Write the traceback to a log file; return the one line that points at it."""
    text = "".join(traceback.format_exception(exc))
    stamp = time.strftime("%Y%m%d-%H%M%S")
    where = None
    for folder in (log_folder(), Path(tempfile.gettempdir())):
        try:
            folder.mkdir(parents=True, exist_ok=True)
            where = folder / f"ps-lab-bug-{stamp}-{os.getpid()}.log"
            where.write_text(
                f"ps-lab {' '.join(sys.argv[1:])}\n{text}",
                encoding="utf-8",
                errors="backslashreplace",  # a path that is not UTF-8
            )
            break
        except (OSError, ValueError):
            where = None
    if logging.getLogger().isEnabledFor(logging.DEBUG):
        sys.stderr.write(text)
    kind = type(exc).__name__
    detail = str(exc).splitlines()[0] if str(exc) else ""
    log = f"traceback in {where}" if where else "no log could be written"
    return (
        f"internal error (a bug in ps-lab, please report it): {kind}: {detail}; {log}; "
        "-vv prints it"
    )


def os_error_line(exc: OSError) -> str:
    name = exc.filename if exc.filename is not None else ""
    reason = exc.strerror or str(exc)
    return f"{name}: {reason}" if name else reason


# --- the group ----------------------------------------------------------------------------------


class HelpGroup(TyperGroup):
    """A click group whose command list wraps each command's summary instead of cutting it."""

    def format_commands(self, ctx: _click_core.Context, formatter: Any) -> None:
        rows = []
        for name in self.list_commands(ctx):
            command = self.get_command(ctx, name)
            if command is not None and not command.hidden:
                rows.append((name, command.get_short_help_str(limit=1000)))
        if rows:
            with formatter.section("Commands"):
                formatter.write_dl(rows)


def command_group(help: str, **settings: Any) -> typer.Typer:
    """A group of commands under the app (``ps-lab rig ...``): bare, it prints its help.

    ``settings``: more ``typer.Typer`` arguments (``name``).
    """
    return typer.Typer(help=help, no_args_is_help=True, cls=HelpGroup, **HELP_SETTINGS, **settings)


class LabGroup(HelpGroup):
    """The app's click group: one line and exit 2 for every failure, 130 for a signal.

    Bare ``ps-lab`` (and a bare command group such as ``ps-lab rig``) prints its help and exits 0.
    """

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):
        previous = install_signal_handlers()
        guard_commands(self)
        _reported.clear()
        code = 0
        try:
            result = super().main(
                args=args,
                prog_name=prog_name,
                complete_var=complete_var,
                standalone_mode=False,
                **extra,
            )
            code = result if isinstance(result, int) else 0
        except _click_exc.NoArgsIsHelpError as exc:
            typer.echo(exc.ctx.get_help() if exc.ctx else exc.format_message())
            code = 0
        except _click_exc.ClickException as exc:
            code = _say(usage_line(exc), EXIT_USER_ERROR)
        except Exit as exc:
            code = exc.exit_code
        except (Abort, KeyboardInterrupt) as exc:
            code = _say(interrupted_line(exc.__context__ or exc), EXIT_INTERRUPTED)
        if code == EXIT_INTERRUPTED and not _reported:
            # Interrupted outside a command body (while parsing): typer exits 130 silently.
            code = _say("interrupted", EXIT_INTERRUPTED)
        if code == 0:
            HELD.print_held()
        else:
            HELD.discard()
        restore_signal_handlers(previous)
        if standalone_mode:
            sys.exit(code)
        return code
