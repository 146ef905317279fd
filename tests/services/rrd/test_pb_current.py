"""The committed protobuf code is what the committed .proto files generate."""

from services.rrd.pb.generate import ROOT, generate


def test_generated_code_is_current(tmp_path):
    written = generate(tmp_path)
    folders = {p.parent.relative_to(tmp_path) for p in written}
    committed_files = {f.relative_to(ROOT) for folder in folders for f in (ROOT / folder).glob("*_pb2*.py*")}
    assert {p.relative_to(tmp_path) for p in written} == committed_files
    for path in written:
        committed = (ROOT / path.relative_to(tmp_path)).read_text()
        assert path.read_text() == committed, f"{path.name} is stale: run python -m services.rrd.pb.generate"
