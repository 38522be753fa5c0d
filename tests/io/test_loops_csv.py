import numpy as np
import pytest

from radarslam.errors import DataError
from radarslam.geometry import se2_to_matrix
from radarslam.io.loops import LoopCandidate, NodeKey, read_loops_csv, write_loops_csv


def test_loops_csv_round_trip(tmp_path):
    loops = [
        LoopCandidate(
            NodeKey("scene-0001", 40),
            NodeKey("scene-0001", 3),
            4_000_000,
            300_000,
            0.25,
            True,
            "ok",
            se2_to_matrix(1.5, -0.5, 3.0),
            0.9,
            0.3,
            0.7,
            tight_fitness=0.15,
            source="proximity",
            constraint_ratio=0.83,
        ),
        LoopCandidate(
            NodeKey("scene-0002", 1),
            NodeKey("scene-0001", 9),
            9_000_000,
            900_000,
            0.61,
            False,
            "fitness 0.20 < 0.5; overlap 0.10 < 0.35",
        ),
    ]
    path = tmp_path / "loops.csv"
    write_loops_csv(path, loops)
    back = read_loops_csv(path)
    assert [(lc.query, lc.candidate, lc.accepted, lc.reason) for lc in back] == [
        (lc.query, lc.candidate, lc.accepted, lc.reason) for lc in loops
    ]
    np.testing.assert_allclose(
        back[0].candidate_from_query, loops[0].candidate_from_query, atol=1e-12
    )
    assert back[0].fitness == 0.9 and np.isnan(back[1].fitness)
    assert (back[0].tight_fitness, back[0].source) == (0.15, "proximity")
    assert np.isnan(back[1].tight_fitness) and back[1].source == "recognition"
    assert back[0].constraint_ratio == 0.83 and np.isnan(back[1].constraint_ratio)


def test_loops_csv_without_the_newer_columns_is_still_read(tmp_path):
    # results folders written before tight_fitness and source existed
    path = tmp_path / "loops.csv"
    write_loops_csv(path, [])
    columns = path.read_text().strip().split(",")
    path.write_text(",".join(columns[:-3]) + "\ns,1,2,s,0,1,0.1,1,ok,0.9,0.3,0.7,1.0,2.0,0.5\n")
    (loop,) = read_loops_csv(path)
    assert loop.accepted and loop.fitness == 0.9 and loop.source == "recognition"
    np.testing.assert_allclose(loop.candidate_from_query[:2, 3], [1.0, 2.0])
    assert np.isnan(loop.constraint_ratio)
    # ... and before constraint_ratio existed
    row = "s,1,2,s,0,1,0.1,1,ok,0.9,0.3,0.7,1.0,2.0,0.5,0.2,proximity"
    path.write_text(",".join(columns[:-1]) + "\n" + row + "\n")
    (loop,) = read_loops_csv(path)
    assert loop.tight_fitness == 0.2 and loop.source == "proximity"
    assert np.isnan(loop.constraint_ratio)


def test_loops_csv_errors(tmp_path):
    path = tmp_path / "loops.csv"
    path.write_text("a,b\n")
    with pytest.raises(DataError, match=r"loops\.csv:1: header"):
        read_loops_csv(path)
    write_loops_csv(path, [])
    path.write_text(path.read_text() + "s,1,2,s,0,1,0.1,yes,ok,1,1,1,0,0,0,0.1,recognition,0.9\n")
    with pytest.raises(DataError, match=r"loops\.csv:2: malformed"):
        read_loops_csv(path)
    with pytest.raises(DataError, match="does not exist"):
        read_loops_csv(tmp_path / "none.csv")


def test_binary_loops_csv_is_a_data_error(tmp_path):
    path = tmp_path / "loops.csv"
    path.write_bytes(b"\xfc\x81\x00garbage" * 40)
    with pytest.raises(DataError, match=r"loops\.csv: not a UTF-8 text file"):
        read_loops_csv(path)
    path.write_text("query_session\x00,x\n")
    with pytest.raises(DataError, match=r"loops\.csv"):
        read_loops_csv(path)


def test_loops_are_numbered_by_their_line(tmp_path):
    from radarslam.io.loops import read_loops_csv_numbered

    path = tmp_path / "loops.csv"
    loop = LoopCandidate(NodeKey("s", 1), NodeKey("s", 0), 2, 1, 0.1, False, "fitness")
    write_loops_csv(path, [loop, loop])
    text = path.read_text().splitlines()
    path.write_text("\n".join([text[0], text[1], "", text[2]]) + "\n")
    assert [n for n, _ in read_loops_csv_numbered(path)] == [2, 4]
