"""Code digests for the cache key: a module and the project modules it imports, comments and docstrings excluded."""

from __future__ import annotations

import ast
import hashlib
import os
import sys
from pathlib import Path

from panoworld.io.manifest import REPO_ROOT, json_digest
from panoworld.io.user_cache import read_user_cache, write_user_cache

_CACHE_FILE = f"code_digests-{hashlib.sha256(str(REPO_ROOT).encode()).hexdigest()[:16]}.json"
"""One record per checkout (the runner and its stages share it; another checkout's files never need reading)."""
_CACHE_KEEP = 4096
"""Entries kept in the user cache: the most recently written ones."""
_memo: dict[str, tuple[int, int, str, list[str]]] = {}
"""path -> (mtime_ns, size, digest, imported module names): files are parsed again only when their stat changes."""
_disk_loaded = False
_BY_TEXT_FILE = "code_digests_by_text.json"
"""Digest and imports by the file's bytes and module name, for every checkout: a file whose stat changed but whose
text did not (a checkout, a merge, a copy of the repository) is read and hashed, not parsed."""
_BY_TEXT_KEEP = 4096
_by_text: dict[str, list] | None = None
_by_text_added = False


def _text_key(data: bytes, module: str, is_package: bool) -> str:
    version = f"{sys.version_info[0]}.{sys.version_info[1]}"  # the AST's dump may differ between Python versions
    return f"{version}:{module}:{int(is_package)}:{hashlib.sha256(data).hexdigest()}"


def _load_disk_cache() -> None:
    global _disk_loaded
    if _disk_loaded:
        return
    _disk_loaded = True
    try:
        _memo.update({k: (v[0], v[1], v[2], v[3]) for k, v in read_user_cache(_CACHE_FILE).items() if k not in _memo})
    except (TypeError, IndexError, KeyError):
        pass


def _parsed_by_text() -> dict[str, list]:
    global _by_text
    if _by_text is None:
        _by_text = read_user_cache(_BY_TEXT_FILE)
    return _by_text


def _save_disk_cache() -> None:
    """Merge this process's entries into the file as it is now (other processes, stages and checkouts write it too:
    replacing it with this process's view alone would drop what they added since, to be parsed again), newest last."""
    global _by_text_added
    try:
        on_disk = {k: v for k, v in read_user_cache(_CACHE_FILE).items() if k not in _memo}
    except (TypeError, AttributeError):
        on_disk = {}
    merged = {**on_disk, **_memo}
    write_user_cache(_CACHE_FILE, dict(list(merged.items())[-_CACHE_KEEP:]))
    if _by_text_added and _by_text is not None:
        merged = {**read_user_cache(_BY_TEXT_FILE), **_by_text}
        write_user_cache(_BY_TEXT_FILE, dict(list(merged.items())[-_BY_TEXT_KEEP:]))
        _by_text_added = False


def _strip_docstrings(tree: ast.AST) -> ast.AST:
    """Drop every statement that is a bare string (module/class/function and attribute docstrings)."""
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if isinstance(body, list):
            node.body = [s for s in body if not (isinstance(s, ast.Expr) and isinstance(s.value, ast.Constant)
                                                 and isinstance(s.value.value, str))]
    return tree


def _imports(tree: ast.AST, module: str, is_package: bool) -> list[str]:
    """Absolute names of every module an import statement (at any depth, lazy ones included) may refer to."""
    package = module if is_package else module.rpartition(".")[0]
    out: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                parts = parts[: len(parts) - (node.level - 1)] if node.level > 1 else parts
                base = ".".join(p for p in [*parts, base] if p)
            out.append(base)
            out += [f"{base}.{a.name}" for a in node.names if a.name != "*"]
    return sorted(set(out))


def file_digest(path: Path | str, module: str) -> tuple[str, list[str]]:
    """(digest of the file's AST without docstrings, imported module names); cached by mtime and size, then by the
    file's bytes."""
    global _by_text_added
    key = str(path)
    st = os.stat(key)
    hit = _memo.get(key)
    if hit and hit[0] == st.st_mtime_ns and hit[1] == st.st_size:
        return hit[2], hit[3]
    data = Path(key).read_bytes()
    is_package = os.path.basename(key) == "__init__.py"
    text_key = _text_key(data, module, is_package)
    known = _parsed_by_text().get(text_key)
    if isinstance(known, list) and len(known) == 2 and isinstance(known[0], str) and isinstance(known[1], list):
        digest, imports = known
    else:
        tree = ast.parse(data, filename=key)
        imports = _imports(tree, module, is_package)
        digest = hashlib.sha256(ast.dump(_strip_docstrings(tree), annotate_fields=False).encode()).hexdigest()
        _parsed_by_text()[text_key] = [digest, imports]
        _by_text_added = True
    _memo[key] = (st.st_mtime_ns, st.st_size, digest, imports)
    return digest, imports


_found: dict[tuple[str, tuple[str, ...]], tuple[str, str] | None] = {}


def _find(module: str, roots: tuple[str, ...]) -> tuple[str, str] | None:
    """(file, its path relative to its root in POSIX form) of a project module (package __init__ or .py file under
    one of roots), None outside them."""
    key = (module, roots)
    hit = _found.get(key, False)
    if hit is not False:
        return hit
    hit = None
    top = module.partition(".")[0]
    rel = module.replace(".", os.sep)
    for root in roots:
        if not os.path.exists(os.path.join(root, top)) and not os.path.isfile(os.path.join(root, top + ".py")):
            continue  # numpy, torch, ...: not a project module
        for cand in (os.path.join(root, rel, "__init__.py"), os.path.join(root, rel + ".py")):
            if os.path.isfile(cand):
                hit = (cand, Path(cand).relative_to(root).as_posix())
                break
        if hit:
            break
    _found[key] = hit
    return hit


def code_digests(module: str, roots: list[Path] | None = None, skip: frozenset[str] = frozenset()) -> dict[str, str]:
    """{path relative to its root: digest} of `module`, its parent packages and every project module it imports,
    transitively (imports inside functions included; dynamic `importlib` imports are not followed); the modules named
    in `skip` (the backends a run does not use) and what only they import are left out."""
    root_names = tuple(str(r) for r in (roots or [REPO_ROOT]))
    _load_disk_cache()
    n_before = len(_memo)
    stale = False
    out: dict[str, str] = {}
    seen: set[str] = set()
    todo = [module]
    while todo:
        name = todo.pop()
        if name in seen or name in skip:
            continue
        seen.add(name)
        parts = name.split(".")
        todo += [".".join(parts[:i]) for i in range(1, len(parts))]  # parent packages run on import
        found = _find(name, root_names)
        if found is None:
            continue
        path, rel = found
        before = _memo.get(path)
        digest, imports = file_digest(path, name)
        stale |= before is None or _memo[path][:2] != before[:2]
        out[rel] = digest
        todo += imports
    if stale or len(_memo) != n_before:
        _save_disk_cache()
    return dict(sorted(out.items()))


def stage_roots(module_file: str | Path, module: str) -> list[Path]:
    """The repository root plus the sys.path entry a stage module was found under (a stage outside the repo)."""
    root = Path(module_file).resolve().parents[module.count(".")]
    return [REPO_ROOT] if root == REPO_ROOT else [REPO_ROOT, root]


def combined(digests: dict[str, str]) -> str:
    """One digest of {file: digest} (what the cache key holds)."""
    return json_digest(digests)


def changed_files(old: dict[str, str] | None, new: dict[str, str]) -> list[str]:
    """Files added, removed or edited between two {file: digest} records."""
    old = old or {}
    return sorted(f for f in set(old) | set(new) if old.get(f) != new.get(f))
