"""Provenance of a store: what defines its data, and what may differ between two runs of it.

Owns the identity a run is resumed against (schema, scene TOML, seed, N, params, package
versions: :func:`identity`), how two identities are compared and their first difference named,
the package versions and checkout commit a session records, and timestamps.
"""

from __future__ import annotations

import json
import platform
import subprocess
import sys
import tomllib
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path
from typing import Any, Iterable, Mapping

import numpy as np

from .schema import STORE_FORMAT, Schema

__all__ = ["DEFAULT_PACKAGES", "package_versions", "git_commit", "sessions", "warn_if_code_changed", "utc_now",
           "json_normal", "identity", "comparable", "first_difference", "check_versions"]

DEFAULT_PACKAGES = (
    "jointsim", "numpy", "scipy", "warp-lang", "mujoco", "gmsh", "trimesh",
    "meshio", "h5py", "pypardiso",
)


def package_versions(packages: Iterable[str] = DEFAULT_PACKAGES) -> dict[str, str]:
    """Installed versions of ``packages`` (distribution names; absent ones left out) and Python."""
    out = {"python": platform.python_version()}
    for p in packages:
        try:
            out[p] = metadata.version(p)
        except metadata.PackageNotFoundError:
            if p == "jointsim":
                from .. import __version__

                out[p] = __version__
    return out


def git_commit() -> str | None:
    """The checkout's commit (with ``-dirty`` for uncommitted changes to tracked files), if any."""
    root = Path(__file__).resolve().parents[2]
    try:
        head = subprocess.run(["git", "-C", root, "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10)
        if head.returncode:
            return None
        dirty = subprocess.run(
            ["git", "-C", root, "status", "--porcelain", "--untracked-files=no"], capture_output=True, text=True, timeout=10
        )
        return head.stdout.strip() + ("-dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return None


def sessions(partial: Path) -> list[dict]:
    """The run's session records, oldest first; not the hidden temporary file of an opener that
    is writing its own (atomic_path's ``.name.*.json``, which the glob would match)."""
    files = sorted(p for p in (partial / "sessions").glob("*.json") if not p.name.startswith("."))
    return [json.loads(p.read_text()) for p in files]


def warn_if_code_changed(partial: Path, commit: str | None) -> None:
    """Warn (stderr) when a run is resumed from another jointsim checkout commit than earlier
    sessions: the package version check cannot see a development commit change, and records
    written before and after may then differ (a solver change moves equilibria)."""
    if commit is None:
        return
    earlier = {s.get("jointsim_git") for s in sessions(partial)} - {None, commit}
    if earlier:
        print(
            f"warning: resuming {partial} with jointsim commit {commit}; earlier sessions ran "
            f"{', '.join(sorted(earlier))} (records from each are kept; see its sessions/ files)",
            file=sys.stderr,
        )


def utc_now(timespec: str = "milliseconds") -> str:
    """The current UTC time in ISO 8601 (provenance timestamps)."""
    return datetime.now(timezone.utc).isoformat(timespec=timespec)


def json_normal(x: Any, what: str) -> Any:
    try:
        return json.loads(json.dumps(x, sort_keys=True, allow_nan=False))
    except (TypeError, ValueError) as e:
        raise ValueError(f"{what} must be JSON-serialisable with finite numbers: {e}") from None


def identity(
    schema: Schema, scene_toml: str, seed: int | None, n_records: int | None, params: Mapping[str, Any] | None,
    versions: Mapping[str, str],
) -> dict[str, Any]:
    if not isinstance(scene_toml, str):
        raise TypeError(f"scene_toml must be the scene file's text, got {type(scene_toml).__name__}")
    try:
        tomllib.loads(scene_toml)
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"scene_toml is not valid TOML: {e}") from None
    if seed is not None and not (isinstance(seed, (int, np.integer)) and seed >= 0):
        raise ValueError(f"seed = {seed!r}: an integer ≥ 0, or None")
    if n_records is not None and not (isinstance(n_records, (int, np.integer)) and n_records >= 1):
        raise ValueError(f"n_records = {n_records!r}: an integer ≥ 1, or None when not known yet")
    ident = {
        "store_format": STORE_FORMAT,
        "schema": schema.to_json(),
        "scene_toml": scene_toml,
        "seed": None if seed is None else int(seed),
        "n_records": None if n_records is None else int(n_records),
        "params": dict(params or {}),
        "versions": dict(versions),
    }
    return json_normal(ident, "params")


def comparable(ident: Mapping[str, Any]) -> dict[str, Any]:
    """The identity as compared on resume: the scene parsed (comments and layout may change),
    schema fields keyed by name so a difference names the field, versions left out."""
    d = {k: v for k, v in ident.items() if k not in ("versions", "scene_toml")}
    d["scene"] = tomllib.loads(ident["scene_toml"])
    s = ident["schema"]
    d["schema"] = {
        "name": s["name"], "version": s["version"], "field order": [f["name"] for f in s["fields"]],
        "fields": {f["name"]: {k: v for k, v in f.items() if k != "name"} for f in s["fields"]},
    }
    return d


def first_difference(a: Any, b: Any, path: str = "") -> str | None:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b), key=str):
            if k not in a or k not in b:
                old, new = (repr(m[k]) if k in m else "absent" for m in (a, b))
                return f"{path}{k}: {old} in the store, {new} now"
            if d := first_difference(a[k], b[k], f"{path}{k}."):
                return d
        return None
    return None if a == b else f"{path.rstrip('.')}: {a!r} in the store, {b!r} now"


def check_versions(stored: Mapping[str, str], here: Mapping[str, str], where: Path) -> None:
    diff = [f"{p} {stored[p]} in the store, {here.get(p, 'absent')} here" for p in stored if stored[p] != here.get(p)]
    if diff:
        raise ValueError(
            f"{where}: package versions differ from the run's ({'; '.join(diff)}); results may not "
            "match bit for bit. Pass allow_version_change=True to mix them anyway."
        )
