"""`python runner.py weights list|fetch|resolve`: what every learned backend needs, fetching it, and where an id resolves."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from panoworld.framework.hub.fetch import Fetched, FetchError, fetch
from panoworld.framework.hub.registry import REGISTRY, WeightsEntry
from panoworld.framework.hub.resolve import (
    HfId,
    WeightsNotFound,
    hub_cache_dir,
    resolve_hf,
    resolve_weights,
    weights_dir,
)
from panoworld.io.safe_write import check_output_dir


def _cached_sizes() -> dict[str, int]:
    """Size on disk of each repo in the local hub cache (huggingface_hub.scan_cache_dir)."""
    try:
        from huggingface_hub import scan_cache_dir

        return {r.repo_id.lower(): r.size_on_disk for r in scan_cache_dir(hub_cache_dir()).repos}
    except Exception:  # no cache directory yet, or huggingface_hub absent: nothing cached
        return {}


def entry_status(entry: WeightsEntry, cached_sizes: dict[str, int] | None = None) -> dict:
    """{state: present|missing|incomplete|trained, path, commit, on_disk} of one registry entry (reads the disk only)."""
    if entry.trained:
        return {"state": "trained", "path": None, "detail": f"trained by this project: {entry.trained}"}
    if entry.repo:
        try:
            root, commit = resolve_hf(HfId(entry.repo, entry.revision if entry.revision != "main" else None))
        except (WeightsNotFound, ImportError):
            return {"state": "missing", "path": None, "detail": f"not in {hub_cache_dir()}"}
        lacks = [f.path for f in entry.files if not (root / f.path).exists()]
        size = (cached_sizes or {}).get(entry.repo.lower())
        return {"state": "incomplete" if lacks else "present", "path": str(root), "commit": commit, "on_disk": size,
                "detail": f"lacks {', '.join(lacks)}" if lacks else f"commit {commit[:12]}"}
    paths = [weights_dir() / f.path for f in entry.files]
    lacks = [p.name for p, f in zip(paths, entry.files) if not p.is_file() or (f.size is not None and p.stat().st_size != f.size)]
    state = "present" if not lacks else "missing" if len(lacks) == len(paths) else "incomplete"
    return {"state": state, "path": str(weights_dir()), "detail": f"lacks {', '.join(lacks)}" if lacks else str(weights_dir())}


def entry_dict(entry: WeightsEntry, status: dict) -> dict:
    return {
        "name": entry.name, "model": entry.model, "kind": entry.kind, "source": entry.source, "repo": entry.repo,
        "revision": entry.revision if entry.repo else None, "size": entry.size, "licence": entry.licence,
        "files": [{"path": f.path, "url": f.url, "size": f.size, "sha256": f.sha256} for f in entry.files],
        "params": [u.param for u in entry.uses], "trained_by": entry.trained, "notes": entry.notes, "status": status,
    }


def usage_lines(result: Fetched, *, to_given: bool) -> list[str]:
    """The `--set` flags, scene.yaml params and other commands that use fetched weights."""
    entry = result.entry
    sets, yaml_params, flags = [], {}, []
    for use in entry.uses:
        if use.file is not None:
            value = str(result.files[use.file])
        elif entry.repo and not to_given:
            value = f"hf:{entry.repo}" + (f"@{entry.revision}" if entry.revision != "main" else "")
        elif entry.repo:
            value = str(result.location)
        else:
            value = str(next(iter(result.files.values())))
        if " " in use.param:  # a flag of another verb: `eval --lpips-weights`
            verb, flag = use.param.split(" ", 1)
            flags.append((verb, [*use.also, f"{flag} {value}"]))
            continue
        for kv in (*use.also, f"{use.param}={value}"):
            key, _, v = kv.partition("=")
            stage, _, param = key.partition(".")
            sets.append(f"--set {key}={v}")
            yaml_params.setdefault(stage, {})[param] = v
    lines = []
    if sets:
        lines.append(f"python runner.py run SCENE {' '.join(dict.fromkeys(sets))}")
        lines.append("or in SCENE/scene.yaml:")
        lines.append("  params:")
        for stage, kv in yaml_params.items():
            lines.append(f"    {stage}: {{{', '.join(f'{k}: {v}' for k, v in kv.items())}}}")
    by_verb: dict[str, list[str]] = {}
    for verb, parts in flags:
        by_verb.setdefault(verb, []).extend(p for p in parts if p not in by_verb.get(verb, []))
    lines += [f"python runner.py {verb} SCENE {' '.join(parts)}" for verb, parts in by_verb.items()]
    if not lines and entry.repo:
        ref = str(result.location) if to_given else f"hf:{entry.repo}" + (f"@{entry.revision}" if entry.revision != "main" else "")
        lines.append(f"use it as a weights param value: {ref}")
    return lines


def cmd_list(args) -> int:
    sizes = _cached_sizes()
    rows = [entry_dict(e, entry_status(e, sizes)) for e in REGISTRY.values()]
    if args.json:
        print(json.dumps({"hub_cache": str(hub_cache_dir()), "weights_dir": str(weights_dir()), "weights": rows}, indent=2))
        return 0
    print(f"Hugging Face cache: {hub_cache_dir()}   release files: {weights_dir()}\n")
    for r in rows:
        st = r["status"]
        print(f"{r['name']:<24} {st['state']:<10} {r['size']}  [{r['licence']}]")
        print(f"{'':<24} {r['model']}")
        print(f"{'':<24} source: {r['source']}")
        print(f"{'':<24} takes it: {', '.join(r['params'])}   ({st['detail']})")
    return 0


def cmd_fetch(args) -> int:
    if args.to is not None:
        check_output_dir(args.to)
    code = 0
    for name in args.names:
        try:
            result = fetch(name, to=args.to)
        except (FetchError, WeightsNotFound, ImportError) as e:
            print(f"error: {e}", file=sys.stderr)
            code = 1
            continue
        where = f"{result.location}" + (f" (commit {result.commit[:12]})" if result.commit else "")
        print(f"{result.entry.name}: {where}")
        for note in result.notes:
            print(f"  {note}")
        for line in usage_lines(result, to_given=args.to is not None):
            print(f"  {line}")
    return code


def cmd_resolve(args) -> int:
    try:
        rec = resolve_weights(args.spec)
    except WeightsNotFound as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(rec, indent=2))
    else:
        print(rec["path"] + ("  (missing)" if rec.get("missing") else ""))
        if rec.get("commit"):
            print(f"commit {rec['commit']}")
        for rel, f in rec["files"].items():
            print(f"  {rel}  {f['size']} bytes  {f['digest']}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python runner.py weights", description=__doc__)
    sub = parser.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("list", help="every learned backend's weights: source, size, licence, param, local state")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_list)
    p = sub.add_parser("fetch", help="download weights (hub snapshot or release URL), verify them, print how to use them")
    p.add_argument("names", nargs="+", metavar="NAME", help="registry name (see `weights list`) or hf:ORG/NAME[@REVISION]")
    p.add_argument("--to", type=Path, help="download into this folder instead of the standard caches")
    p.set_defaults(func=cmd_fetch)
    p = sub.add_parser("resolve", help="where a weights value (hf: id or path) resolves offline, with file digests")
    p.add_argument("spec", help="hf:ORG/NAME[@REVISION][/PATH] or a local path")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=cmd_resolve)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
