"""The committed protobuf code is what the committed .proto files generate."""

from services.rrd.pb.generate import PB_DIR, generate


def test_generated_code_is_current(tmp_path):
    written = generate(tmp_path)
    assert {p.name for p in written} == {p.name for p in PB_DIR.glob("*_pb2*.py*")}
    for path in written:
        committed = (PB_DIR / path.name).read_text()
        assert path.read_text() == committed, f"{path.name} is stale: run python -m services.rrd.pb.generate"
