"""The exported networks as ONNX graphs (``d2spo export --onnx``; the extra ``d2spo[onnx]``).

Written with the ``onnx`` library's helper API from the layers the manifest lists: each dense layer
is a ``Gemm`` (x @ kernel + bias) followed by its activation node. Three graphs, batch axis ``N``:

* ``policy.onnx``: (obs [N, D], and for D²SPO x [N, K + 1]) -> action [N, 2], u_rl [N, 2]: π_rl and,
  for D²SPO, π_Ω(x, u_rl) (x is b(z, O_s): the lidar ranges in metres and the nearest-obstacle
  distance, ``deploy.Policy.x_of_observation``). The runtime filter is not in it: it iterates and
  differentiates (``deploy.filter``);
* ``cbf.onnx`` (D²SPO): x [N, K + 1] -> h [N, 1];
* ``nominal.onnx`` (D²SPO): s [N, 3], u [N, 2] -> rate [N, 3], the pose's rate of Eq. (5).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from d2spo.deploy.manifest import file_sha256
from d2spo.errors import UserError
from d2spo.runio import atomic_write_bytes

OPSET = 17
"""The ONNX operator set the graphs use (onnxruntime 1.14 and later run it)."""
IR_VERSION = 8
"""The ONNX IR version written (that of opset 17), so older runtimes read the files too."""
_NODES = {"relu": "Relu", "tanh": "Tanh", "sigmoid": "Sigmoid"}


def _onnx():
    try:
        import onnx
    except ImportError:
        raise UserError("--onnx needs the onnx package: pip install 'd2spo[onnx]'") from None
    return onnx


class _Graph:
    """Nodes and initialisers of one graph under construction."""

    def __init__(self, onnx, arrays: dict):
        self.onnx, self.arrays = onnx, arrays
        self.nodes, self.inits, self.n = [], [], 0

    def name(self, stem: str) -> str:
        self.n += 1
        return f"{stem}_{self.n}"

    def const(self, value: np.ndarray, stem: str = "c") -> str:
        name = self.name(stem)
        self.inits.append(self.onnx.numpy_helper.from_array(np.asarray(value, np.float32), name))
        return name

    def const_int(self, value: list[int]) -> str:
        name = self.name("i")
        self.inits.append(self.onnx.numpy_helper.from_array(np.asarray(value, np.int64), name))
        return name

    def op(self, kind: str, inputs: list[str], stem: str | None = None, **attrs) -> str:
        out = self.name(stem or kind.lower())
        self.nodes.append(self.onnx.helper.make_node(kind, inputs, [out], **attrs))
        return out

    def dense(self, x: str, layer: dict) -> str:
        y = self.op("Gemm", [x, self.const(self.arrays[layer["kernel"]], "kernel"),
                             self.const(self.arrays[layer["bias"]], "bias")])
        return y if layer["activation"] == "linear" else self.op(_NODES[layer["activation"]], [y])

    def mlp(self, x: str, layers: list[dict]) -> str:
        for layer in layers:
            x = self.dense(x, layer)
        return x

    def network_input(self, x: str, H: float) -> str:
        """concat(x / H, min(x) / H) (``safety.cbf.network_input``)."""
        scaled = self.op("Div", [x, self.const(np.float32(H), "H")])
        low = self.op("ReduceMin", [scaled], axes=[1], keepdims=1)
        return self.op("Concat", [scaled, low], axis=1)

    def model(self, inputs: list[tuple[str, int]], outputs: list[tuple[str, str, int]], doc: str):
        """A checked model; ``outputs``: (graph name, the tensor to expose, width)."""
        h = self.onnx.helper
        for public, inner, _ in outputs:
            self.nodes.append(h.make_node("Identity", [inner], [public]))
        tensor = lambda name, width: h.make_tensor_value_info(name, self.onnx.TensorProto.FLOAT, ["N", width])  # noqa: E731
        graph = h.make_graph(self.nodes, doc.split(":")[0], [tensor(n, w) for n, w in inputs],
                             [tensor(n, w) for n, _, w in outputs], self.inits)
        model = h.make_model(graph, opset_imports=[h.make_opsetid("", OPSET)], producer_name="d2spo export",
                             doc_string=doc)
        model.ir_version = IR_VERSION
        self.onnx.checker.check_model(model, full_check=True)
        return model


def write_onnx(out: Path, manifest: dict, arrays: dict) -> dict:
    """Write the graphs of the manifest's networks into ``out``; returns the manifest's ``onnx`` entry."""
    onnx = _onnx()
    nets, H = manifest["networks"], manifest["sensor"]["sensing_radius"]
    D, K1 = manifest["observation"]["size"], manifest["sensor"]["n_rays"] + 1
    m = manifest["action"]["size"]
    models = {}
    g = _Graph(onnx, arrays)
    u_rl = g.mlp("obs", nets["actor"]["layers"])
    if "safety_policy" not in nets:
        models["policy"] = (g.model([("obs", D)], [("action", u_rl, m), ("u_rl", u_rl, m)],
                                    "policy: the actor's action for observations obs"), ["obs"])
    else:
        sp = nets["safety_policy"]
        trunk = g.mlp(g.op("Concat", [g.network_input("x", H), u_rl], axis=1), sp["hidden"])
        beta, a = g.dense(trunk, sp["beta"]), g.dense(trunk, sp["a"])
        u = g.op("Add", [u_rl, g.op("Mul", [beta, g.op("Sub", [a, u_rl])])])
        models["policy"] = (g.model([("obs", D), ("x", K1)], [("action", u, m), ("u_rl", u_rl, m)],
                                    "policy: pi_Omega(x, pi_rl(obs)), x the lidar ranges (m) and the nearest "
                                    "obstacle's distance"), ["obs", "x"])
        g = _Graph(onnx, arrays)
        h = g.mlp(g.network_input("x", H), nets["cbf"]["layers"])
        models["cbf"] = (g.model([("x", K1)], [("h", h, 1)], "cbf: the learned barrier h(x)"), ["x"])
        g = _Graph(onnx, arrays)
        theta = g.op("Slice", ["s", g.const_int([2]), g.const_int([3]), g.const_int([1])])
        inp = g.op("Concat", [g.op("Cos", [theta]), g.op("Sin", [theta]), "u"], axis=1)
        rate = g.mlp(inp, nets["nominal"]["layers"])
        models["nominal"] = (g.model([("s", 3), ("u", m)], [("rate", rate, 3)],
                                     "nominal: the pose's rate f_n(s, u) of Eq. (5)"), ["s", "u"])
    entry = {}
    for name, (model, inputs) in models.items():
        path = Path(out) / f"{name}.onnx"
        atomic_write_bytes(path, model.SerializeToString())
        entry[name] = {"file": path.name, "sha256": file_sha256(path), "inputs": inputs,
                       "outputs": [o.name for o in model.graph.output], "opset": OPSET}
    return entry
