import pytest

from radarslam.io.atomic import atomic_open, atomic_path, write_json_atomic


def test_interrupted_write_keeps_old_file(tmp_path):
    path = tmp_path / "metrics.json"
    write_json_atomic(path, {"a": 1})
    with pytest.raises(RuntimeError), atomic_open(path) as fh:
        fh.write('{"a": 2, "trunc')
        raise RuntimeError("killed mid-write")
    assert path.read_text().strip().startswith('{\n  "a": 1')
    assert [p.name for p in tmp_path.iterdir()] == ["metrics.json"]


def test_atomic_path_moves_only_on_success(tmp_path):
    target = tmp_path / "plot.png"
    with atomic_path(target) as tmp:
        tmp.write_bytes(b"png")
        assert not target.exists()
    assert target.read_bytes() == b"png"
    with pytest.raises(ValueError), atomic_path(target) as tmp:
        tmp.write_bytes(b"half")
        raise ValueError
    assert target.read_bytes() == b"png"
    assert len(list(tmp_path.iterdir())) == 1
