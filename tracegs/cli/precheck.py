"""The command line checked before Hydra writes anything.

Hydra creates the run folder (a product folder: the run's identity names it) with ``.hydra/`` and the job log
before the task runs, so a command refused by validation would still write into the folder of a finished
product; ``--cfg job`` prints a config without validating it, misspelt ``+`` keys included. Here the overrides
are parsed and the job's config composed and validated first (the task validates it again, under Hydra).
"""

from __future__ import annotations

import shlex
import sys

from hydra import compose, initialize_config_dir
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.errors import HydraException, MissingConfigException, OverrideParseException
from omegaconf.errors import ConfigAttributeError, ConfigKeyError, OmegaConfBaseException

from tracegs.cli.failures import USER_ERRORS
from tracegs.config.validate import validate
from tracegs.errors import one_line

# Hydra's own flags that print or run something other than one job of the task.
_NOT_ONE_JOB = {"-m", "--multirun", "--help", "-h", "--hydra-help", "--info", "-i", "--version", "--shell-completion",
                "-sc", "--run", "-r"}
_CFG_FLAGS = {"--cfg", "-c"}
QUOTE_HINT = ("quote a value holding ',', '=', spaces or brackets (a path pasted from a log, say): "
              "key='/path/with,commas'; in a shell wrap the whole override in double quotes")
# Characters bash still reads inside double quotes (and '!', history expansion in an interactive shell).
_BASH_DOUBLE_QUOTED = set('"$`\\!')
_QUOTES = ("'", '"')


def shell_override(override: str) -> str | None:
    """``key=value`` as one bash word that reaches Hydra as a quoted value it reads back exactly (None when the
    override is not ``key=value``): Hydra's single quotes, with each quote in the value escaped (``\\'``), inside
    bash's double quotes, which keep that backslash; where the value holds a character bash reads inside double
    quotes, bash's single quotes (shlex) instead."""
    key, equals, value = override.partition("=")
    if not equals or not key:
        return None
    if len(value) >= 2 and value[0] == value[-1] and value[0] in _QUOTES:  # quoted already, but not as Hydra reads it
        value = value[1:-1]
    # Hydra reads a backslash as an escape before a quote only: a trailing one, before the closing quote, doubled.
    body = value.rstrip("\\")
    hydra = f"{key}='" + body.replace("'", "\\'") + "\\" * 2 * (len(value) - len(body)) + "'"
    return shlex.quote(hydra) if set(value) & _BASH_DOUBLE_QUOTED else f'"{hydra}"'


def quote_hint(override: str) -> str:
    """The advice for an override Hydra's grammar refuses: the override itself as it must be typed in bash."""
    typed = shell_override(override)
    return QUOTE_HINT if typed is None else f"quote it for Hydra and the shell, in bash: {typed}"


def overrides_of(argv: list[str]) -> list[str]:
    """The overrides on a command line (what is not a flag or a flag's argument)."""
    flags_with_values = {"--cfg", "-c", "--package", "-p", "--config-path", "-cp", "--config-name", "-cn",
                         "--config-dir", "-cd", "--experimental-rerun", "--info", "-i"}
    overrides, skip = [], False
    for arg in argv:
        if skip:
            skip = False
            continue
        if arg in flags_with_values:
            skip = arg not in ("--info", "-i")  # --info's argument is optional and never holds '='
            continue
        if not arg.startswith("-"):
            overrides.append(arg)
    return overrides


def parse_error(overrides: list[str], multirun: bool) -> str | None:
    """One line naming the first override Hydra's grammar refuses (or, outside ``-m``, reads as a sweep), with
    the hint to quote it; None if all parse."""
    parser = OverridesParser.create()
    for override in overrides:
        try:
            (parsed,) = parser.parse_overrides([override])
            if parsed.is_sweep_override() and not multirun:
                return f"the override {override!r} reads as a sweep over several values: {quote_hint(override)}"
        except OverrideParseException as error:
            reasons = [line.strip() for line in str(error).splitlines()
                       if line.strip() and not line.startswith(("Error parsing", "See "))]
            return (f"cannot parse the override {override!r} ({(reasons or ['syntax error'])[0]}): "
                    f"{quote_hint(override)}")
    return None


def check_command_line(config_dir: str, config_name: str, argv: list[str]) -> str | None:
    """The one-line refusal of this command line, or None to go on: a parse error, or (for one job, ``--cfg job``
    included) the first error of composing and validating its config."""
    overrides = overrides_of(argv)
    error = parse_error(overrides, multirun=bool({"-m", "--multirun"} & set(argv)))
    if error is not None or set(argv) & _NOT_ONE_JOB:
        return error
    if set(argv) & _CFG_FLAGS:
        position = max(argv.index(flag) for flag in set(argv) & _CFG_FLAGS) + 1
        if position < len(argv) and argv[position] in ("hydra", "all"):
            return None
    try:
        with initialize_config_dir(config_dir=config_dir, version_base="1.3"):
            validate(compose(config_name=config_name, overrides=overrides))
    except USER_ERRORS as refused:
        return one_line(refused.args[0] if isinstance(refused, KeyError) and refused.args else refused, limit=2000)
    except (HydraException, OmegaConfBaseException) as refused:
        return composition_error(refused)
    return None


def composition_error(error: BaseException) -> str:
    """One line for an override Hydra cannot compose, naming the field or group. Hydra's own report is 7-12
    lines and, for a misspelt key, suggests the ``+`` that validation then refuses."""
    cause = error.__cause__ if error.__cause__ is not None else error
    if isinstance(error, MissingConfigException) and error.missing_cfg_file:
        group, _, option = error.missing_cfg_file.rpartition("/")
        listing = str(error).partition("Available options in")[2].partition("Config search path")[0]
        options = [line.strip() for line in listing.splitlines()[1:] if line.strip()]
        return f"config group '{group}' has no option '{option}'" + (f" (one of: {', '.join(options)})" if options else "")
    field = getattr(cause, "full_key", None)
    if isinstance(cause, (ConfigAttributeError, ConfigKeyError)) and field:
        return f"config field '{field}': is not a field of the schema (misspelt?); see --cfg job for the valid keys"
    if isinstance(cause, OmegaConfBaseException) and field:
        return f"config field '{field}': {one_line(str(cause).splitlines()[0])}"
    return one_line(error)


def refuse_bad_command_line(app: str, config_dir: str, config_name: str, argv: list[str]) -> None:
    """Exit with code 2 and one line on stderr when :func:`check_command_line` refuses ``argv``."""
    message = check_command_line(config_dir, config_name, argv)
    if message is not None:
        print(f"tracegs-{app}: error: {message}", file=sys.stderr)
        sys.exit(2)
