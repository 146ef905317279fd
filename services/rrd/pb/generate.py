"""Regenerate the committed protobuf/gRPC Python code: `python -m services.rrd.pb.generate`.

Two folders of protos: the RRD wire format and the message proxy (`services/rrd/pb`), and the
catalog protocol (`services/redap/pb`, which imports the first). A test regenerates into a
temporary folder and fails if the committed files differ.
"""

from __future__ import annotations

import sys
from pathlib import Path

PB_DIR = Path(__file__).resolve().parent
ROOT = PB_DIR.parents[2]  # the folder holding the `services` package
REDAP_DIR = ROOT / "services" / "redap" / "pb"
# (folder, proto, with gRPC stubs)
PROTOS = (
    (PB_DIR, "common.proto", False),
    (PB_DIR, "log_msg.proto", False),
    (PB_DIR, "sdk_comms.proto", True),
    (REDAP_DIR, "cloud.proto", True),
)


def generate(out_root: Path) -> list[Path]:
    """Write the generated modules under `out_root/services/.../pb/`; return their paths."""
    from grpc_tools import protoc  # dev dependency: only needed to regenerate

    include = Path(protoc.__file__).parent / "_proto"  # google/protobuf/*.proto
    written: list[Path] = []
    for folder, proto, with_grpc in PROTOS:
        rel = folder.relative_to(ROOT)
        (out_root / rel).mkdir(parents=True, exist_ok=True)
        args = ["protoc", f"-I{ROOT}", f"-I{include}", f"--python_out={out_root}", f"--pyi_out={out_root}"]
        if with_grpc:
            args.append(f"--grpc_python_out={out_root}")
        if protoc.main([*args, str(rel / proto)]) != 0:
            raise RuntimeError(f"protoc failed on {proto}")
        stem = proto.removesuffix(".proto")
        written += sorted((out_root / rel).glob(f"{stem}_pb2*.py*"))
    return written


if __name__ == "__main__":
    written = generate(ROOT)
    print("\n".join(str(p.relative_to(ROOT)) for p in written))
    sys.exit(0)
