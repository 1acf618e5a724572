"""The pipeline runner: cache decisions with reasons and locked transactional runs over the DAG of pipeline.yaml."""

from __future__ import annotations

import dataclasses
import json
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from panoworld.core.errors import InputError, PipelineError
from panoworld.core.params import flatten
from panoworld.framework import uptodate
from panoworld.framework.dag import Pipeline, StageNode, text_digest
from panoworld.framework.execute import StageExecutor, failure_line, pending_log, refusal_file, run_subprocess
from panoworld.framework.lock import SceneLock
from panoworld.framework.resolve import parse_sets, resolve_params
from panoworld.framework.scene import ARTIFACTS_DIRNAME, SCENE_CONFIG, Scene, input_paths, open_scene
from panoworld.io import manifest as art

if TYPE_CHECKING:
    import subprocess

# The stage contract (panoworld.framework.stage), the kernels and the weights hub are imported where they are used: a
# replayed no-op (uptodate) needs none of them.

__all__ = ["PipelineError", "Pipeline", "Report", "StageResult", "open_scene", "parse_sets", "resolve_params", "run",
           "stage_state", "status"]


@dataclass
class StageResult:
    stage: str
    action: str
    """'ran' | 'cached' | 'failed' | 'skipped' (and 'would-run' in a dry run)."""
    reason: str
    seconds: float = 0.0
    peak_rss_mb: float | None = None
    bad_input: bool = False
    """A failure because the stage refused its input (its exit code 2): the runner exits 2."""

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclass
class Report:
    scene: Path
    results: list[StageResult] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    """What the run did not do in full without failing: files left out, panoramas not registered."""
    compile_process: subprocess.Popen | None = field(default=None, repr=False, compare=False)
    """The background compilation of numba kernels this run started on a cold cache (kernels.start_background_compile;
    None when none): it may outlive the run."""

    @property
    def ok(self) -> bool:
        return all(r.action != "failed" for r in self.results)

    def as_dict(self) -> dict[str, Any]:
        return {"scene": str(self.scene), "stages": [r.as_dict() for r in self.results], "notes": self.notes}

    def table(self) -> str:
        rows = [("stage", "action", "reason", "seconds", "peak MB")]
        for r in self.results:
            mem = f"{r.peak_rss_mb:.0f}" if r.peak_rss_mb is not None else "-"
            rows.append((r.stage, r.action, r.reason, f"{r.seconds:.2f}", mem))
        widths = [min(max(len(row[i]) for row in rows), 70) for i in range(5)]
        fmt = lambda row: "  ".join(c[:70].ljust(w) if i < 3 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths)))
        return "\n".join([fmt(rows[0]), "  ".join("-" * w for w in widths)] + [fmt(r) for r in rows[1:]]
                         + [f"note: {n}" for n in self.notes])


def _diff_params(stage: str, old: dict, new: dict) -> str:
    old, new = flatten(old), flatten(new)
    keys = sorted(set(old) | set(new))
    diffs = [f"{stage}.{k} {json.dumps(old.get(k))} -> {json.dumps(new.get(k))}" for k in keys if old.get(k) != new.get(k)]
    return "params changed: " + ", ".join(diffs)


def stage_state(node: StageNode, scene: Scene, params: Any) -> tuple[bool, str]:
    """(up_to_date, reason) for one stage given the artifacts on disk now."""
    from panoworld.framework import code_digest
    from panoworld.framework.hub import resolve as hub
    from panoworld.framework.stage import input_digest, resolve_stage_weights, stage_code, stage_key
    from panoworld.framework.stage_params import params_hash, params_to_dict

    out_dir = scene.artifact_dir(node.name)
    if not out_dir.exists():
        return False, "no artifact yet"
    try:
        manifest = art.read_manifest(out_dir, node.spec.artifact)
    except art.ArtifactError as e:
        return False, f"invalid artifact: {e}"
    problem = art.verify_files(out_dir, manifest)
    if problem:
        return False, problem
    try:
        digests = {r.name: input_digest(r.name, node.spec.inputs[r.name], p) for r, p in zip(node.inputs, input_paths(node, scene).values())}
        for name, spec in node.spec.inputs.items():  # an optional input the DAG does not wire (the stage sees None)
            if name not in digests:
                digests[name] = input_digest(name, spec, None)
    except InputError as e:
        return False, f"input not ready: {e}"
    try:
        weights = resolve_stage_weights(params, manifest.get("weights"), stage=node.name)
    except InputError as e:
        return False, f"weights missing: {e}"
    pdict = params_to_dict(params)
    code = stage_code(node.spec, params)
    key = stage_key(node.spec, params, digests, weights, code)
    if key == manifest["key"]:
        return True, "up to date"
    if manifest["stage_version"] != node.spec.version:
        return False, f"code version changed: {manifest['stage_version']} -> {node.spec.version}"
    old_code = (manifest.get("code") or {}).get("files")
    if old_code is None:
        return False, "code changed: no code digest recorded (an artifact of an older runner)"
    changed_code = code_digest.changed_files(old_code, code)
    if changed_code:
        more = f" (+{len(changed_code) - 5} more)" if len(changed_code) > 5 else ""
        return False, f"code changed: {', '.join(changed_code[:5])}{more}"
    if manifest["params_hash"] != params_hash(pdict):
        return False, _diff_params(node.name, manifest["params"], pdict)
    changed_weights = hub.describe_change(node.name, manifest.get("weights") or {}, weights)
    if changed_weights:
        return False, changed_weights
    changed = [n for n, d in digests.items() if manifest["inputs"].get(n, {}).get("digest") != d]
    return False, f"input changed: {', '.join(changed) or 'unknown'}"


# ---------------------------------------------------------------- running


def _select(pipeline: Pipeline, only: list[str], from_: str | None, until: str | None) -> tuple[set[str], set[str]]:
    """(selected stages, stages forced to rerun by the selection itself)."""
    for s in only:
        pipeline.check_stage(s, "--only")
    if from_:
        pipeline.check_stage(from_, "--from")
    if until:
        pipeline.check_stage(until, "--until")
    if only and (from_ or until):
        raise PipelineError("--only cannot be combined with --from/--until")
    if only:
        return set(only), set()
    selected = set(pipeline.order)
    forced: set[str] = set()
    if from_:
        selected = {from_} | pipeline.descendants(from_)
        forced = set(selected)
    if until:
        selected &= {until} | pipeline.ancestors(until)
        forced &= selected
    return selected, forced



def run(
    scene_dir: Path | str,
    *,
    only: list[str] = (),
    from_: str | None = None,
    until: str | None = None,
    force: bool = False,
    sets: list[str] = (),
    preset: str | None = None,
    dry_run: bool = False,
    keep_going: bool = False,
    echo: bool = False,
    pipeline: Pipeline | None = None,
    on_result: Callable[[StageResult], None] | None = None,
    variant: tuple[str, list[str]] | None = None,
    execute: StageExecutor | None = None,
) -> Report:
    """Bring the scene's artifacts up to date; the library API behind `runner.py run`."""
    pipeline = pipeline or Pipeline.load()
    selected, forced = _select(pipeline, list(only), from_, until)
    set_map = parse_sets(list(sets), pipeline)
    plain = not (only or from_ or until or force or dry_run) and variant is None and execute is None
    if plain:
        replayed = _replay(_record_key(pipeline, Path(scene_dir).absolute(), _config_digest(scene_dir), preset, sets),
                           scene_dir, on_result)
        if replayed is not None:
            return replayed
    from panoworld.framework import kernels
    from panoworld.framework.hub import resolve as hub

    scene = open_scene(scene_dir, pipeline)
    if variant is not None:  # the variant's --set values override the run's; their stages and descendants are its tail
        name, vsets = variant
        vmap = parse_sets(list(vsets), pipeline)
        for stage, values in vmap.items():
            set_map.setdefault(stage, {}).update(values)
        tail = set(vmap).union(*(pipeline.descendants(st) for st in vmap))
        scene = dataclasses.replace(scene, variant=name, tail=frozenset(tail))
    params = resolve_params(pipeline, preset, scene, set_map, [n for n in pipeline.order if n in selected or n in set_map])
    key = _record_key(pipeline, scene.root, scene.config_digest, preset, sets) if plain else None
    if force:
        forced |= selected
    if not dry_run:  # an `hf:` weights id missing from the local cache: one line naming `weights fetch`, nothing run
        for name in (n for n in pipeline.order if n in selected):
            try:
                hub.check_params_weights(params[name], where=f"{name}.")
            except hub.WeightsNotFound as e:
                raise PipelineError(str(e)) from None
    report = Report(scene.root, notes=list(scene.notes))

    def emit(r: StageResult):
        report.results.append(r)
        if on_result:
            on_result(r)

    if dry_run:
        for name in pipeline.order:
            node = pipeline.stages[name]
            if name not in selected:
                emit(StageResult(name, "skipped", "not selected"))
                continue
            up, why = stage_state(node, scene, params[name])
            stale_up = [u for u in pipeline.upstream(name) if any(r.stage == u and r.action == "would-run" for r in report.results)]
            if name in forced:
                emit(StageResult(name, "would-run", "forced (--force/--from)" if up else why))
            elif stale_up and not only:
                emit(StageResult(name, "would-run", f"upstream will rerun: {', '.join(stale_up)}"))
            else:
                emit(StageResult(name, "would-run" if not up else "cached", why))
        return report

    blocked: set[str] = set()  # stages that failed or were skipped because of a failure
    compiling: list = []
    fresh = not scene.artifacts.exists()
    with SceneLock(scene) as lock:
        watch = _watch(pipeline, scene) if key is not None else None
        for name in pipeline.order:
            node = pipeline.stages[name]
            art.recover_dir(scene.artifact_dir(name))
            if name not in selected:
                emit(StageResult(name, "skipped", "not selected"))
                continue
            bad_up = [u for u in pipeline.upstream(name) if u in blocked]
            if bad_up:
                blocked.add(name)
                emit(StageResult(name, "skipped", f"upstream {', '.join(bad_up)} failed"))
                continue
            missing = [
                f"{r.name} ({r.source + '.' if r.source == 'scene' else 'stage '}{r.target})"
                for r, p in zip(node.inputs, input_paths(node, scene).values())
                if p is None and not r.optional
            ]
            if missing:
                blocked.add(name)
                emit(StageResult(name, "failed", f"missing input: {', '.join(missing)}; run the upstream stage first"))
                if not keep_going:
                    break
                continue
            up, why = stage_state(node, scene, params[name])
            if up and name not in forced:
                emit(StageResult(name, "cached", why))
                continue
            reason = "forced" if up else why
            if execute is None and not compiling:  # numba's cache cold: its kernels compile while earlier stages run
                compiling = [kernels.start_background_compile(home=scene.files.get("panoramas") is not None)
                             if selected & set(kernels.KERNEL_STAGES) else None]
                report.compile_process = compiling[0]
            waited = kernels.wait_for_stage(compiling[0], name) if execute is None else 0.0
            if echo and waited >= 1.0:
                print(f"[{name}] waited {waited:.1f} s for its numba kernels (compiled once, in the background)",
                      file=sys.stderr, flush=True)
            code, secs, rss = (execute or run_subprocess)(node, scene, params[name], echo)
            if code == 0:
                try:
                    rss = art.read_manifest(scene.artifact_dir(name), node.spec.artifact)["peak_rss_mb"]
                except art.ArtifactError:
                    pass  # keep the (upper-bound) figure of wait4
                emit(StageResult(name, "ran", reason, secs, rss))
            elif code == 2:  # the stage refused its input: one line, its log not kept
                blocked.add(name)
                part, refusal = pending_log(scene.log_file(name)), refusal_file(scene.log_file(name))
                why = refusal.read_text().strip() if refusal.is_file() else failure_line(part, name)
                part.unlink(missing_ok=True)
                refusal.unlink(missing_ok=True)
                emit(StageResult(name, "failed", f"bad input: {why or 'see the stage output above'}", secs, rss,
                                 bad_input=True))
            else:
                blocked.add(name)
                why = failure_line(scene.log_file(name), name)
                emit(StageResult(name, "failed", f"exit code {code}: {why}; log: {scene.log_file(name)}" if why else
                                 f"exit code {code}; log: {scene.log_file(name)}", secs, rss))
                if not keep_going:
                    break
        done = {r.stage for r in report.results}
        for name in pipeline.order:
            if name not in done:
                emit(StageResult(name, "skipped", "not run: an earlier stage failed (use --keep-going)"))
        if fresh and not any(r.action == "ran" for r in report.results):
            lock.remove_bookkeeping()  # nothing committed into a new artifacts/: leave the scene as it was
        report.notes.extend(scene_notes({r.stage: scene.artifact_dir(r.stage) for r in report.results
                                         if r.action in ("ran", "cached")}, scene.root))
        if key is not None:
            _record(key, pipeline, scene, params, report, watch)
    return report


def scene_notes(artifacts: dict[str, Path], root: Path) -> list[str]:
    """The notes a scene's artifacts ({STAGE: artifact dir} of the stages that are up to date) call for under the run
    table and in `status`: the panoramas the depth stage levelled, a home that registration left partly unplaced
    or levelled for itself, and a home whose floor is NavMesh pieces that do not connect."""
    from panoworld.framework.notes import floor_pieces_note
    from panoworld.io.home import level_note
    from panoworld.register.artifact import registration_note

    notes = [level_note(artifacts["depth"]) if "depth" in artifacts else None,
             registration_note(artifacts["register"], root) if "register" in artifacts else None,
             floor_pieces_note(artifacts["navmesh"], artifacts.get("register")) if "navmesh" in artifacts else None]
    return [n for n in notes if n]


def _record_key(pipeline: Pipeline, root: Path, config_digest: str | None, preset: str | None, sets) -> str:
    """The up-to-date record's key of a plain run: its arguments and the texts of pipeline.yaml and scene.yaml."""
    return uptodate.record_key(root, pipeline.path, [pipeline.text_digest, config_digest, preset, list(sets)])


def _config_digest(scene_dir: Path | str) -> str | None:
    try:
        return text_digest((Path(scene_dir) / SCENE_CONFIG).read_text(errors="replace"))
    except OSError:
        return None


def _watch(pipeline: Pipeline, scene: Scene) -> tuple[list[str], list] | None:
    """(paths, their stats now) of what this run's decisions read (uptodate.watched_paths); None when no record can
    stand for them."""
    paths = uptodate.watched_paths(scene.root, pipeline.path, [(scene.artifact_dir(n), pipeline.stages[n].spec.module)
                                                                for n in pipeline.order])
    return None if paths is None else (paths, uptodate.stats(paths))


def _record(key: str, pipeline: Pipeline, scene: Scene, params: dict[str, Any], report: Report,
            watch: tuple[list[str], list] | None) -> None:
    """After a plain run under the lock: record what a no-op of the same arguments reports while nothing it read
    changes (uptodate); the stats are those taken before the decisions that found every stage up to date (for a run
    that ran stages, decided again here)."""
    if [r.stage for r in report.results] != pipeline.order or any(r.action not in ("cached", "ran") for r in report.results):
        uptodate.drop(key)
        return
    results = report.results
    if any(r.action == "ran" for r in results):
        watch = _watch(pipeline, scene)
        if watch is not None:
            results = [StageResult(n, "cached", why) for n in pipeline.order
                       for up, why in [stage_state(pipeline.stages[n], scene, params[n])] if up]
    if watch is None or len(results) != len(pipeline.order):
        uptodate.drop(key)
        return
    uptodate.save(key, *watch, [r.as_dict() for r in results], list(report.notes))


def _replay(key: str, scene_dir: Path | str, on_result: Callable[[StageResult], None] | None) -> Report | None:
    """The report a plain run recorded (_record) when none of the files its decisions read has changed since, checked
    under the scene lock; None otherwise."""
    root = Path(scene_dir).absolute()
    if not (root / ARTIFACTS_DIRNAME).is_dir():
        return None
    with SceneLock(Scene(root, {}, {})):
        rec = uptodate.replayable(key)
        try:
            report = Report(root, notes=[str(n) for n in rec["notes"]], results=[StageResult(**r) for r in rec["results"]])
        except (TypeError, KeyError):  # no record, or not one this runner wrote
            return None
        for r in report.results:
            if on_result:
                on_result(r)
    return report


def status(scene_dir: Path | str, *, preset: str | None = None, sets: list[str] = (), pipeline: Pipeline | None = None) -> list[dict]:
    """Each stage's state and reason, and its artifact's path and schema version (reads manifests, hashes nothing big)."""
    pipeline = pipeline or Pipeline.load()
    scene = open_scene(scene_dir, pipeline)
    set_map = parse_sets(list(sets), pipeline)
    all_params = resolve_params(pipeline, preset, scene, set_map, pipeline.order)  # bad params: exit 2 before any row
    rows = []
    for name in pipeline.order:
        node = pipeline.stages[name]
        params = all_params[name]
        up, why = stage_state(node, scene, params)
        d = scene.artifact_dir(name)
        sv = None
        if (d / art.MANIFEST).is_file():
            try:
                sv = json.loads((d / art.MANIFEST).read_text()).get("schema_version")
            except (OSError, json.JSONDecodeError):
                sv = None
        rows.append(
            {
                "stage": name,
                "state": "up-to-date" if up else "stale",
                "reason": why,
                "artifact": str(d),
                "schema": node.spec.artifact,
                "schema_version": sv,
                "accepted_schema_versions": art.accepted_schema_versions(node.spec.artifact),
            }
        )
    return rows
