"""Checkpoints: the training state and its counters, verified when read, with one fallback.

A checkpoint directory (a run directory, or the group directory of ``train.train_seeds``) holds::

    checkpoint.json        the manifest, and the commit point: format, generation, the state file's
                           name, size and SHA-256, the SHA-256 of the run's config.json, the
                           counters, and the manifest's own SHA-256
    checkpoint-G.msgpack   the training state of generation G (flax msgpack)
    checkpoint.prev.json   the manifest of the checkpoint before it, whose state file is kept

Saving generation G writes the state file (temporary file, fsync, rename), then replaces
checkpoint.json (the commit), then replaces checkpoint.prev.json with the manifest it displaced,
then deletes the state files neither manifest names. A kill at any moment leaves checkpoint.json
naming a complete state. Reading checks every checksum and the state's array shapes; a damaged
checkpoint is reported in one warning and the previous one is used; a config.json changed since
the checkpoint is refused.

Directories written before this format (``checkpoint.json`` holding only the counters, the state
in ``checkpoint.msgpack``) still load, without the checksum and config checks they never
recorded; their next save writes this format.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jax
import msgpack
import numpy as np
from flax import serialization

from d2spo.errors import RunDirError, RunDirWarning
from d2spo.runio import atomic_write_bytes, atomic_write_parts, read_json, remove_file

FORMAT = 2
MANIFEST = "checkpoint.json"
PREVIOUS = "checkpoint.prev.json"
LEGACY_STATE = "checkpoint.msgpack"
_STATE = re.compile(r"^checkpoint-(\d+)\.msgpack$")
_COUNTERS = ("episodes", "env_steps", "chunks")


def fingerprint(obj: Any) -> str:
    """SHA-256 of the canonical JSON of ``obj`` (sorted keys, no spaces)."""
    return hashlib.sha256(_canonical(obj)).hexdigest()


def run_fingerprint(run_dir: Path) -> str:
    """The fingerprint of a run directory's config.json, as a checkpoint records it."""
    return fingerprint(read_json(Path(run_dir) / "config.json", "the run's config"))


def has_checkpoint(directory: Path) -> bool:
    return (Path(directory) / MANIFEST).is_file() or (Path(directory) / PREVIOUS).is_file()


def load_checkpoint(directory: Path, template: Any, config_sha256: str | None = None) -> tuple[Any, dict]:
    """(state, counters) of the newest usable checkpoint in ``directory``; see ``Checkpoints.load``."""
    return Checkpoints(directory, config_sha256).load(template)


class _Damaged(Exception):
    """A checkpoint that cannot be used as it is; the message says why."""


class DamagedState(ValueError):
    """A saved pytree (a checkpoint's state, a policy file) that cannot be restored onto the
    config's template; the message, one line, names the file and why."""


def restore_bytes(template: Any, data: bytes, name: str) -> Any:
    """``data`` (flax's msgpack, ``serialization.to_bytes``) restored onto ``template``'s structure.
    Raises ``DamagedState`` when it cannot be read (truncated, not msgpack) or when its arrays'
    count, shapes or dtypes are not the template's (written with another config): flax alone would
    restore such arrays as they are, and the first program that uses them would fail."""
    try:
        state = serialization.from_bytes(template, data)
    except Exception as e:  # noqa: BLE001 - a damaged or foreign file fails in many ways
        raise DamagedState(f"{name} cannot be restored ({type(e).__name__})") from None
    got = jax.tree_util.tree_flatten_with_path(state)[0]
    want = jax.tree_util.tree_leaves(template)
    if len(got) != len(want):
        raise DamagedState(f"{name} holds {len(got)} arrays where this config builds {len(want)}; "
                           "was it written with another config?")
    for (where, a), b in zip(got, want):
        if np.shape(a) != tuple(b.shape) or np.asarray(a).dtype != b.dtype:
            raise DamagedState(f"{name} holds {jax.tree_util.keystr(where)} as {np.asarray(a).dtype}"
                               f"{list(np.shape(a))} where this config builds {b.dtype}{list(b.shape)}; "
                               "was it written with another config?")
    return state


@dataclass
class _Manifest:
    file: str            # checkpoint.json or checkpoint.prev.json
    raw: bytes           # its bytes, as written
    generation: int
    state: str           # the state file's name
    size: int | None     # None: a checkpoint of the earlier format, never checksummed
    sha256: str | None
    config_sha256: str | None
    meta: dict


_STREAMED_BYTES = 1 << 16
"""Arrays of at least this many bytes are written from their own memory (``state_parts``)."""


def state_parts(state: Any):
    """The bytes of ``flax.serialization.to_bytes(state)``, the same bytes, as a sequence of parts:
    each large array (``_STREAMED_BYTES`` or more) is one part that is a view of its own memory,
    framed as flax frames it (a msgpack ext of type ``ndarray`` holding (shape, dtype name, raw
    bytes)). ``to_bytes`` built three copies of the whole state (each array's bytes, its ext, the
    map): 1.1-1.6 s for the 161 MB state of ϕ1's learner, against 0.35 s to write and fsync it
    (bench/RESULTS.md, "2026-12-03, late night"). States flax would split into chunks (an array
    over ``serialization.MAX_CHUNK_SIZE``) are serialised by flax, as one part."""
    tree = serialization.to_state_dict(state)
    if any(getattr(x, "nbytes", 0) > serialization.MAX_CHUNK_SIZE for x in jax.tree_util.tree_leaves(tree)):
        yield serialization.msgpack_serialize(tree)
        return
    yield from _parts(tree, msgpack.Packer())


def _parts(node: Any, packer: msgpack.Packer):
    if type(node) is dict:  # msgpack's map: its header, then each key and value (flax packs strict types)
        yield packer.pack_map_header(len(node))
        for key, value in node.items():
            yield packer.pack(key)
            yield from _parts(value, packer)
        return
    if isinstance(node, (np.ndarray, jax.Array)) and node.nbytes >= _STREAMED_BYTES:
        arr = np.ascontiguousarray(np.asarray(node))
        if not (arr.dtype.hasobject or arr.dtype.isalignedstruct):
            # flax: ExtType(ndarray, packb((shape, dtype name, arr.tobytes("C")))); bin 32 and ext 32,
            # as msgpack picks for payloads of 64 KiB and more
            head = (packer.pack_array_header(3) + packer.pack(list(arr.shape)) + packer.pack(arr.dtype.name)
                    + b"\xc6" + arr.nbytes.to_bytes(4, "big"))
            yield b"\xc9" + (len(head) + arr.nbytes).to_bytes(4, "big") + bytes([serialization._MsgpackExtType.ndarray])
            yield head
            yield memoryview(arr.reshape(-1).view(np.uint8))
            return
    yield serialization.msgpack_serialize(node)


class Checkpoints:
    """Saves and loads the checkpoints of one directory (see the module's docstring)."""

    def __init__(self, directory: Path, config_sha256: str | None):
        self.dir = Path(directory)
        self.config_sha256 = config_sha256
        self.latest: dict | None = None  # counters of the newest checkpoint saved, loaded, or found
        self._previous: _Manifest | None = None  # becomes checkpoint.prev.json at the next save
        self.generation = max([_generation(p.name) for p in self._state_files()] or [0])
        try:  # a verified manifest already here (e.g. a seed's own directory when its group resumes)
            current = self._manifest(MANIFEST)
        except (_Damaged, OSError):
            current = None
        if current is not None:
            self.latest, self._previous = current.meta, current
            self.generation = max(self.generation, current.generation)

    # ----------------------------------------------------------------------------------- read
    def load(self, template: Any) -> tuple[Any, dict]:
        """The state (a host pytree shaped like ``template``) and counters of the newest usable
        checkpoint. A damaged newest one gives a ``RunDirWarning`` and the previous one; a
        checkpoint of another config.json, or none usable, a ``RunDirError``."""
        if not has_checkpoint(self.dir):
            kept = " (a shared run without its checkpoints: its kept policy, policy-best.msgpack, runs without --policy last)" \
                if (Path(self.dir) / "policy-best.msgpack").is_file() else ""
            raise RunDirError(f"{self.dir}: no checkpoint ({MANIFEST}); has the run written one yet?{kept}")
        failed: list[str] = []
        for name in (MANIFEST, PREVIOUS):
            if not (self.dir / name).is_file():
                failed.append(f"{name}: missing")
                continue
            try:
                m = self._manifest(name)
                self._check_config(m)
                state = self._restore(m, template)
            except _Damaged as e:
                failed.append(f"{name}: {e}")
                continue
            if failed:
                warnings.warn(f"{self.dir}: {failed[0]}; using the previous checkpoint "
                              f"({_describe(m.meta)}) instead", RunDirWarning, stacklevel=3)
            self.latest, self._previous = m.meta, m
            self.generation = max(self.generation, m.generation)
            return state, m.meta
        raise RunDirError(f"{self.dir}: no usable checkpoint ({'; '.join(failed)})")

    def _manifest(self, name: str) -> _Manifest:
        raw = (self.dir / name).read_bytes()
        try:
            data = json.loads(raw)
        except ValueError:
            raise _Damaged("not valid JSON") from None
        if not isinstance(data, dict):
            raise _Damaged("not a JSON object")
        if "format" not in data:  # the earlier format: the counters alone, state in checkpoint.msgpack
            _check_meta(data)
            return _Manifest(name, raw, 0, LEGACY_STATE, None, None, None, data)
        if data.get("format") != FORMAT:
            raise _Damaged(f"format {data.get('format')!r} is not one this d2spo reads ({FORMAT})")
        body = {k: v for k, v in data.items() if k != "manifest_sha256"}
        if data.get("manifest_sha256") != fingerprint(body):
            raise _Damaged("fails its own SHA-256 check (damaged or edited)")
        missing = [k for k in ("generation", "state", "state_bytes", "state_sha256", "config_sha256", "meta")
                   if k not in data]
        if missing:
            raise _Damaged(f"field {missing[0]!r} is missing")
        if not isinstance(data["state"], str) or not _STATE.match(data["state"]):
            raise _Damaged(f"field 'state' names no state file: {data['state']!r}")
        _check_meta(data["meta"])
        return _Manifest(name, raw, _generation(data["state"]), data["state"], data["state_bytes"],
                         data["state_sha256"], data["config_sha256"], data["meta"])

    def _check_config(self, m: _Manifest) -> None:
        if self.config_sha256 is not None and m.config_sha256 is not None and m.config_sha256 != self.config_sha256:
            raise RunDirError(f"{self.dir}: {m.file} was written for another config.json (config.json changed "
                              "after the run started); restore it, or start a new run with another --out")

    def _restore(self, m: _Manifest, template: Any) -> Any:
        path = self.dir / m.state
        if not path.is_file():
            raise _Damaged(f"its state file {m.state} is missing")
        data = path.read_bytes()
        if m.size is not None and len(data) != m.size:
            raise _Damaged(f"{m.state} holds {len(data)} bytes, not {m.size}")
        if m.sha256 is not None and hashlib.sha256(data).hexdigest() != m.sha256:
            raise _Damaged(f"{m.state} fails its SHA-256 check")
        try:
            return restore_bytes(template, data, m.state)
        except DamagedState as e:
            raise _Damaged(str(e)) from None

    # ---------------------------------------------------------------------------------- write
    def save(self, state: Any, meta: dict) -> None:
        """Write ``state`` (a pytree) and ``meta`` (the counters) as the next generation."""
        if self.config_sha256 is None:
            raise ValueError("Checkpoints.save needs the config's fingerprint")
        _check_meta(meta)
        gen = self.generation + 1
        name = f"checkpoint-{gen}.msgpack"
        digest, size = hashlib.sha256(), 0

        def parts():
            nonlocal size
            for part in state_parts(state):
                digest.update(part)
                size += len(part)
                yield part

        atomic_write_parts(self.dir / name, parts())
        body = {"format": FORMAT, "generation": gen, "state": name, "state_bytes": size,
                "state_sha256": digest.hexdigest(), "config_sha256": self.config_sha256, "meta": meta}
        raw = (json.dumps({**body, "manifest_sha256": fingerprint(body)}, indent=2, sort_keys=True) + "\n").encode()
        atomic_write_bytes(self.dir / MANIFEST, raw)  # the commit
        previous = self._previous
        if previous is not None and previous.size is None:  # the earlier format: checksum it now
            previous = self._adopt_legacy(previous)
        if previous is not None:
            atomic_write_bytes(self.dir / PREVIOUS, previous.raw)
        else:
            remove_file(self.dir / PREVIOUS)
        keep = {name} | ({previous.state} if previous is not None else set())
        for p in self._state_files():
            if p.name not in keep:
                remove_file(p)
        self.generation = gen
        self.latest = json.loads(json.dumps(meta))
        self._previous = _Manifest(MANIFEST, raw, gen, name, size, body["state_sha256"], self.config_sha256,
                                   self.latest)

    def _adopt_legacy(self, m: _Manifest) -> _Manifest:
        """A format-2 manifest for a checkpoint of the earlier format (already loaded and checked)."""
        data = (self.dir / m.state).read_bytes()
        body = {"format": FORMAT, "generation": 0, "state": m.state, "state_bytes": len(data),
                "state_sha256": hashlib.sha256(data).hexdigest(), "config_sha256": self.config_sha256, "meta": m.meta}
        raw = (json.dumps({**body, "manifest_sha256": fingerprint(body)}, indent=2, sort_keys=True) + "\n").encode()
        return _Manifest(PREVIOUS, raw, 0, m.state, len(data), body["state_sha256"], self.config_sha256, m.meta)

    def tidy(self) -> None:
        """Delete state files no manifest names (a kill between a save's steps leaves them). Only
        for the directory's lock holder: a reader must not delete what a writer is writing."""
        named = set()
        for name in (MANIFEST, PREVIOUS):
            try:
                data = json.loads((self.dir / name).read_bytes())
            except FileNotFoundError:
                continue
            except (OSError, ValueError):
                return  # cannot tell what it names: keep everything
            named.add(data.get("state", LEGACY_STATE) if isinstance(data, dict) else LEGACY_STATE)
        for p in self._state_files():
            if p.name not in named:
                remove_file(p)

    def _state_files(self) -> list[Path]:
        if not self.dir.is_dir():
            return []
        return [p for p in self.dir.iterdir() if _STATE.match(p.name) or p.name == LEGACY_STATE]


def _generation(name: str) -> int:
    m = _STATE.match(name)
    return int(m.group(1)) if m else 0


def _canonical(obj: Any) -> bytes:
    return json.dumps(obj, sort_keys=True, separators=(",", ":")).encode()


def _describe(meta: dict) -> str:
    return f"after episode {meta['episodes']}" if "episodes" in meta else "of the group"


def _check_meta(meta: Any) -> None:
    """The counters of a run, or ``{"runs": [counters or null, ...]}`` for a group: a damaged or
    edited field is reported by name."""
    if isinstance(meta, dict) and "runs" in meta:
        runs = meta["runs"]
        if not isinstance(runs, list):
            raise _Damaged("field 'runs' is not a list")
        for r in runs:
            if r is not None:
                _check_meta(r)
        return
    if not isinstance(meta, dict):
        raise _Damaged("the counters are not a JSON object")
    for k in _COUNTERS:
        v = meta.get(k)
        if not isinstance(v, int) or isinstance(v, bool) or v < 0:
            raise _Damaged(f"field {k!r} must be a non-negative integer, not {v!r}")
    v = meta.get("wall_seconds")
    if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or v < 0:
        raise _Damaged(f"field 'wall_seconds' must be a non-negative number, not {v!r}")
