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


def test_unwritable_targets_are_data_errors_naming_the_path(tmp_path):
    from radarslam.errors import DataError
    from radarslam.io.atomic import write_text_atomic

    (tmp_path / "metrics.json").mkdir()
    with pytest.raises(DataError, match=r"metrics\.json: cannot write \(Is a directory\)"):
        write_json_atomic(tmp_path / "metrics.json", {"a": 1})
    (tmp_path / "plots").write_text("not a folder")
    with pytest.raises(DataError, match=r"plots/a\.png: cannot write \(.*plots is a file"):
        write_text_atomic(tmp_path / "plots" / "a.png", "x")
    with pytest.raises(DataError, match=r"plots/b\.png: cannot write \(.*plots is a file"):
        with atomic_path(tmp_path / "plots" / "b.png") as tmp:
            tmp.write_bytes(b"png")
    (tmp_path / "dir.png").mkdir()
    with pytest.raises(DataError, match=r"dir\.png: cannot write"):
        with atomic_path(tmp_path / "dir.png") as tmp:
            tmp.write_bytes(b"png")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir.png", "metrics.json", "plots"]


def test_atomic_files_get_the_umask_mode(tmp_path):
    import os

    old = os.umask(0o027)
    try:
        write_json_atomic(tmp_path / "a.json", {})
        with atomic_path(tmp_path / "b.png") as tmp:
            tmp.write_bytes(b"png")
    finally:
        os.umask(old)
    assert (tmp_path / "a.json").stat().st_mode & 0o777 == 0o640
    assert (tmp_path / "b.png").stat().st_mode & 0o777 == 0o640


def test_write_errors_stay_oserrors_for_callers_that_tolerate_them(tmp_path):
    # e.g. the radar index cache: a read-only folder must not stop the reader
    import errno

    from radarslam.errors import DataError

    (tmp_path / "cache.npz").mkdir()
    with pytest.raises(OSError) as err:
        write_json_atomic(tmp_path / "cache.npz", {})
    assert isinstance(err.value, DataError) and err.value.errno == errno.EISDIR
    assert str(err.value) == f"{tmp_path / 'cache.npz'}: cannot write (Is a directory)"


def test_a_fifo_is_written_as_a_stream_and_stays_a_fifo(tmp_path):
    import os
    import stat
    import threading

    fifo = tmp_path / "out.json"
    os.mkfifo(fifo)
    got: list[bytes] = []

    def drain():
        with open(fifo, "rb") as fh:
            got.append(fh.read())

    for write in (
        lambda: write_json_atomic(fifo, {"a": 1}),
        lambda: _library_writes(fifo, b"plot bytes"),
    ):
        reader = threading.Thread(target=drain)
        reader.start()
        write()
        reader.join(timeout=10)
        assert not reader.is_alive()
    assert got == [b'{\n  "a": 1\n}\n', b"plot bytes"]
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.json"]  # no temporary beside it


def _library_writes(path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)  # as savefig or torch.save would


def test_a_socket_is_refused(tmp_path):
    import socket

    from radarslam.io.atomic import WriteError

    path = tmp_path / "s.json"
    with socket.socket(socket.AF_UNIX) as sock:
        sock.bind(str(path))
        with pytest.raises(WriteError, match=r"s\.json: cannot write \(it is a socket, not a file"):
            write_json_atomic(path, {})


def test_a_symbolic_link_is_written_through(tmp_path):
    real = tmp_path / "data" / "metrics.json"
    real.parent.mkdir()
    real.write_text("old")
    link = tmp_path / "metrics.json"
    link.symlink_to(real)
    write_json_atomic(link, {"a": 1})
    assert link.is_symlink() and real.read_text().startswith("{")
    with atomic_path(link) as tmp:
        assert tmp.parent == real.parent
        tmp.write_text("new")
    assert link.is_symlink() and real.read_text() == "new"
    dangling = tmp_path / "later.json"
    dangling.symlink_to(tmp_path / "data" / "later.json")
    write_json_atomic(dangling, [])
    assert dangling.is_symlink() and (tmp_path / "data" / "later.json").read_text().strip() == "[]"
