"""The `python -m stages.NAME` entry every stage module exposes: CLI flags derived from its params dataclass, then run."""

from __future__ import annotations

import argparse
import dataclasses
import enum
import inspect
import json
import os
import signal
import sys
import traceback
import typing
from pathlib import Path
from typing import Any

from panoworld.core import params as P
from panoworld.core.errors import PanoWorldError, PipelineError, from_os_error
from panoworld.framework.stage import RUNNER_PID_ENV, StageInputError, StageSpec, execute_stage, load_stage
from panoworld.framework.stage_params import field_docs, merge, normalize, params_from_dict, unwrap_optional

REFUSAL_ENV = "PANOWORLD_REFUSAL_FILE"
"""Set by a runner: a stage that refuses its input (exit 2) writes its one line there, for the runner to print once."""


def die_with_runner() -> None:
    """In a stage started by a local runner: be killed when the runner dies (Linux PR_SET_PDEATHSIG), and exit at once
    if it is already gone."""
    pid = os.environ.get(RUNNER_PID_ENV)
    if not pid:
        return
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # 1 = PR_SET_PDEATHSIG
    if os.getppid() != int(pid):
        raise PipelineError(f"the runner (pid {pid}) that started this stage is gone; not running")


def build_parser(spec: StageSpec) -> argparse.ArgumentParser:
    doc = (spec.module.__doc__ or "").strip().splitlines()
    parser = argparse.ArgumentParser(
        prog=f"python -m stages.{spec.name}",
        description=(doc[0] if doc else spec.name) + " Runs without the runner: give inputs and --out explicitly.",
    )
    g_in = parser.add_argument_group("inputs")
    for name, inp in spec.inputs.items():
        what = {"file": "file", "dir": "directory"}.get(inp.kind, f"{inp.kind} artifact directory")
        g_in.add_argument(
            f"--{name.replace('_', '-')}", dest=f"in_{name}", type=Path, required=not inp.optional,
            help=f"{inp.help} ({what}{', optional' if inp.optional else ''})",
        )
    parser.add_argument("--out", type=Path, required=True, help=f"output {spec.artifact} artifact directory")
    parser.add_argument("--params-file", type=Path, help="JSON file of params (flags below override it)")
    _add_param_flags(parser, parser.add_argument_group("params"), spec.params_cls, "")
    return parser


def _add_param_flags(parser: argparse.ArgumentParser, group, cls: type, prefix: str) -> None:
    """One flag per param (`--max-features`), nested backend options as `--wan-steps`; help from the field docstring
    and its declared rule."""
    docs = field_docs(cls)
    hints = typing.get_type_hints(cls)
    for old, new in P.renamed(cls).items():  # old flags keep working, unlisted
        group.add_argument("--" + old.replace("_", "-"), dest="p_" + new.replace(".", "__"), help=argparse.SUPPRESS)
    for f in dataclasses.fields(cls):
        if P.is_options(f):
            sub = parser.add_argument_group(f"{prefix}{f.name} options (--set STAGE.{prefix}{f.name}.PARAM=VALUE)")
            _add_param_flags(parser, sub, hints[f.name], f"{prefix}{f.name}.")
            continue
        tp, _ = unwrap_optional(hints[f.name])
        default = P.plain(f.default) if f.default is not dataclasses.MISSING else None
        rule = P.rule_of(f)
        choices = [m.value for m in tp] if inspect.isclass(tp) and issubclass(tp, enum.Enum) else None
        if rule.choices is not None:
            choices = [P.plain(c) for c in rule.choices]
        allowed = rule.describe()
        name = f"{prefix}{f.name}"
        group.add_argument(
            "--" + name.replace(".", "-").replace("_", "-"), dest="p_" + name.replace(".", "__"), default=None,
            metavar=("{" + ",".join(map(str, choices)) + "}") if choices else tp.__name__.upper() if hasattr(tp, "__name__") else "VALUE",
            help=f"{docs.get(f.name, '')} (default: {default}{'; ' + allowed if allowed and not choices else ''})".replace("%", "%%"),
        )


def _param_flag_values(args: argparse.Namespace) -> dict[str, Any]:
    """{dotted param: value} of the param flags given on the command line."""
    return {k[2:].replace("__", "."): v for k, v in vars(args).items() if k.startswith("p_") and v is not None}


def stage_main(module_name: str, argv: list[str] | None = None) -> int:
    """The thin `main()` every stage module exposes: parse flags from the params dataclass and run."""
    # Before torch loads OpenMP: its idle threads sleep instead of spinning. On a busy 2-core machine spinning
    # threads made one Gaussian ERP render cost 122 CPU-s (222 s wall) instead of 23 (48 s): docs/multi.md, "Speed".
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    spec = load_stage(sys.modules[module_name])
    args = build_parser(spec).parse_args(argv)
    try:
        die_with_runner()
        values: dict[str, Any] = {}
        if args.params_file:
            try:
                values.update(json.loads(args.params_file.read_text()))
            except (OSError, json.JSONDecodeError) as e:
                raise StageInputError(f"--params-file {args.params_file}: {e}") from None
        try:
            flags = normalize(spec.params_cls, _param_flag_values(args), spec.name)
            values = merge(normalize(spec.params_cls, values, spec.name), flags)
            params = params_from_dict(spec.params_cls, values, where=spec.name)
        except ValueError as e:
            raise StageInputError(str(e)) from None
        inputs = {name: getattr(args, f"in_{name}") for name in spec.inputs}
        manifest = execute_stage(spec, inputs, params, args.out)
    except PanoWorldError as e:
        refusal = os.environ.get(REFUSAL_ENV)
        if refusal and e.exit_code == 2:
            Path(refusal).write_text(str(e))
        else:
            print(f"error: stage {spec.name}: {e}", file=sys.stderr)
        return e.exit_code
    except OSError as e:  # the environment (full disk, read-only output): one line
        err = from_os_error(e)
        if err.exit_code != 2:
            traceback.print_exc()  # kept in the stage's log; the runner shows the line below
        print(f"error: stage {spec.name}: {err}", file=sys.stderr)
        return err.exit_code
    print(
        f"{spec.name}: wrote {args.out} ({len(manifest['files'])} files, {manifest['wall_s']:.2f} s, "
        f"peak {manifest['peak_rss_mb']:.0f} MB)",
        file=sys.stderr,
    )
    return 0
