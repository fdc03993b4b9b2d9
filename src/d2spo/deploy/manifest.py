"""What ``d2spo export`` writes and ``deploy.Policy.load`` reads, besides the networks: the manifest's
format and versions, its file names, its checksums (of each file, and of the manifest itself without
its checksum), and the check that its settings are ones this runtime has. docs/deploy.md describes
the artefact.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

FORMAT = "d2spo-policy"
"""The manifest's ``format``."""
FORMAT_VERSION = 2
"""The manifest's ``format_version`` ``d2spo export`` writes: 2 since 2026-12-03, a manifest that always
records its ``CONTENT_KEY``. This runtime also reads version 1 (the same keys; the checksum optional)."""
FORMAT_VERSIONS = (1, 2)
"""The ``format_version``s this runtime reads."""
CHECKSUMMED_SINCE = 2
"""The first ``format_version`` whose manifests always record ``CONTENT_KEY``: one without it is damaged
or edited (version 1 predates the key, and its exports from before 2026-12-02 lack it)."""
MANIFEST = "manifest.json"
WEIGHTS = "weights.npz"


def file_sha256(path: Path) -> str:
    """SHA-256 of the file's bytes, as hex."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


CONTENT_KEY = "content_sha256"
"""The manifest's own checksum: of its JSON without this key (``content_sha256``)."""


def content_sha256(manifest: dict) -> str:
    """SHA-256 of ``manifest`` without ``CONTENT_KEY``, as canonical JSON (sorted keys, no spaces):
    an edit of any value (the action's scaling, the map, the automaton, the filter) changes it."""
    body = {k: v for k, v in manifest.items() if k != CONTENT_KEY}
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def check_content(m: dict) -> None:
    """ValueError unless the manifest's settings are ones this runtime has: every layer's activation
    named in ``nets.ACTIVATIONS``, the filter's ``alpha`` and the automaton's ``label_mode`` among their
    values, positive finite scales, and an automaton whose transitions stay within its states (the
    checksums catch a damaged copy; this catches a writer or an edit that this runtime would misread:
    an unknown alpha would run as the cubic one, an unknown label mode as ``step``)."""
    from d2spo.deploy.nets import ACTIVATIONS

    def positive(value, what: str) -> None:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value <= 0:
            raise ValueError(f"{what} must be a finite number > 0, got {value!r:.40}")

    nets = m["networks"]
    for name, net in nets.items():
        specs = net["layers"] if "layers" in net else [*net["hidden"], net["beta"], net["a"]]
        for spec in specs:
            if spec["activation"] not in ACTIVATIONS:
                raise ValueError(f"networks.{name}: activation {spec['activation']!r} is not one of "
                                 f"{', '.join(ACTIVATIONS)}")
    act = m["action"]
    for key in ("v_max", "omega_max", "dt"):
        positive(act[key], f"action.{key}")
    v_min = act.get("v_min", -act["v_max"])
    if isinstance(v_min, bool) or not isinstance(v_min, (int, float)) or not -act["v_max"] <= v_min < act["v_max"]:
        raise ValueError(f"action.v_min must lie in [-v_max, v_max), got {v_min!r:.40}")
    positive(m["sensor"]["sensing_radius"], "sensor.sensing_radius")
    positive(m["sensor"]["n_rays"], "sensor.n_rays")
    f = m.get("filter")
    if f is not None:
        if f["alpha"] not in ("linear", "cubic"):
            raise ValueError(f"filter.alpha must be 'linear' or 'cubic', got {f['alpha']!r:.40}")
        for key in ("alpha_coef", "dt", "iters", "n_bisect"):
            positive(f[key], f"filter.{key}")
    aut = m["automaton"]
    if aut["label_mode"] not in ("event", "step"):
        raise ValueError(f"automaton.label_mode must be 'event' or 'step', got {aut['label_mode']!r:.40}")
    delta = np.asarray(aut["delta"])
    n_states, n_letters = len(aut["accepting"]), 2 ** len(aut["aps"])
    if delta.shape != (n_states, n_letters) or not np.issubdtype(delta.dtype, np.integer) \
            or (delta < 0).any() or (delta >= n_states).any() or len(aut["rejecting"]) != n_states \
            or not 0 <= aut["initial"] < n_states:
        raise ValueError(f"automaton: delta must be [{n_states}][{n_letters}] states in 0..{n_states - 1}, with "
                         f"as many accepting and rejecting flags and an initial state among them")
    if any(not 0 <= a["bit"] < n_letters for a in m["layout"]["areas"]):
        raise ValueError(f"layout.areas: a bit outside 0..{n_letters - 1}")
