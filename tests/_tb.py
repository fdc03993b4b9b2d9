"""Reading TensorBoard event files back in the tests (what tensorboardX wrote under a run's tb/)."""

from __future__ import annotations

import struct
from pathlib import Path


def tb_scalars(tb_dir: Path) -> dict[str, list[tuple[int, float]]]:
    """Every scalar of the TensorBoard event files in ``tb_dir``: tag -> [(step, value)], in the
    order written."""
    from tensorboardX.proto import event_pb2

    out: dict[str, list[tuple[int, float]]] = {}
    for f in sorted(Path(tb_dir).glob("events.out.tfevents.*")):
        data, i = f.read_bytes(), 0
        while i < len(data):  # TFRecord: length (u64), its crc (u32), the record, its crc (u32)
            (n,) = struct.unpack("<Q", data[i:i + 8])
            event = event_pb2.Event.FromString(data[i + 12:i + 12 + n])
            i += 16 + n
            for v in event.summary.value:
                out.setdefault(v.tag, []).append((event.step, v.simple_value))
    return out
