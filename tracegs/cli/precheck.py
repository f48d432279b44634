"""The command line checked before Hydra writes anything.

Hydra creates the run folder (a product folder: the run's identity names it) with ``.hydra/`` and the job log
before the task runs, so a command refused by validation would still write into the folder of a finished
product; ``--cfg job`` prints a config without validating it, misspelt ``+`` keys included. Here the overrides
are parsed and the job's config composed and validated first (the task validates it again, under Hydra).
"""

from __future__ import annotations

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
                return f"the override {override!r} reads as a sweep over several values: {QUOTE_HINT}"
        except OverrideParseException as error:
            reasons = [line.strip() for line in str(error).splitlines()
                       if line.strip() and not line.startswith(("Error parsing", "See "))]
            return f"cannot parse the override {override!r} ({(reasons or ['syntax error'])[0]}): {QUOTE_HINT}"
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
