"""Regenerate the committed protobuf/gRPC Python code: `python -m services.rrd.pb.generate`.

A test regenerates into a temporary folder and fails if the committed files differ.
"""

from __future__ import annotations

import sys
from pathlib import Path

PB_DIR = Path(__file__).resolve().parent
ROOT = PB_DIR.parents[2]  # the folder holding the `services` package
PROTOS = ("common.proto", "log_msg.proto", "sdk_comms.proto")
GRPC_PROTOS = ("sdk_comms.proto",)


def generate(out_root: Path) -> list[Path]:
    """Write the generated modules under `out_root/services/rrd/pb/`; return their paths."""
    from grpc_tools import protoc  # dev dependency: only needed to regenerate

    rel = PB_DIR.relative_to(ROOT)
    out_root.mkdir(parents=True, exist_ok=True)
    (out_root / rel).mkdir(parents=True, exist_ok=True)
    for proto in PROTOS:
        args = ["protoc", f"-I{ROOT}", f"--python_out={out_root}", f"--pyi_out={out_root}"]
        if proto in GRPC_PROTOS:
            args.append(f"--grpc_python_out={out_root}")
        if protoc.main([*args, str(rel / proto)]) != 0:
            raise RuntimeError(f"protoc failed on {proto}")
    return sorted((out_root / rel).glob("*_pb2*.py*"))


if __name__ == "__main__":
    written = generate(ROOT)
    print("\n".join(str(p.relative_to(ROOT)) for p in written))
    sys.exit(0)
