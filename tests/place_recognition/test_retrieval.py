import numpy as np
import pytest

from radarslam.errors import DataError
from radarslam.place_recognition.config import RetrievalConfig
from radarslam.place_recognition.retrieval import DescriptorIndex


def test_exact_search_matches_brute_force_and_faiss():
    rng = np.random.default_rng(3)
    db = rng.normal(size=(300, 24)).astype(np.float32)
    q = rng.normal(size=(17, 24)).astype(np.float32)
    idx = DescriptorIndex.from_descriptors(db, RetrievalConfig(chunk_size=5))
    res = idx.search(q, 7)
    d = np.linalg.norm(q[:, None] - db[None], axis=2)
    np.testing.assert_array_equal(res.indices, np.argsort(d, axis=1)[:, :7])
    np.testing.assert_allclose(res.distances, np.sort(d, axis=1)[:, :7], atol=1e-4)
    pytest.importorskip("faiss")
    f = DescriptorIndex.from_descriptors(db, RetrievalConfig(backend="faiss")).search(q, 7)
    np.testing.assert_array_equal(f.indices, res.indices)


def test_incremental_add_ties_and_errors():
    idx = DescriptorIndex(2)
    assert idx.search(np.zeros((1, 2)), 3).indices.shape == (1, 0)
    idx.add(np.array([[1.0, 0.0], [0.0, 1.0]]))
    idx.add(np.array([1.0, 0.0]))
    r = idx.search(np.array([[1.0, 0.0]]), 10)
    assert r.indices.tolist() == [[0, 2, 1]]  # ties in insertion order, k clipped
    with pytest.raises(DataError, match="dimension"):
        idx.add(np.zeros((1, 3)))
    with pytest.raises(DataError, match="NaN"):
        idx.search(np.array([[np.nan, 0.0]]), 1)


def test_matrix_is_a_read_only_view_and_k_is_checked():
    rng = np.random.default_rng(0)
    db = rng.normal(size=(50, 8)).astype(np.float32)
    idx = DescriptorIndex.from_descriptors(db)
    q = db[:3] + 0.01
    before = idx.search(q, 5)
    m = idx.matrix
    np.testing.assert_array_equal(m, db)
    with pytest.raises(ValueError, match="read-only"):
        m[:] = 0
    with pytest.raises(ValueError):
        m.setflags(write=True)
    after = idx.search(q, 5)
    np.testing.assert_array_equal(after.indices, before.indices)
    np.testing.assert_array_equal(after.distances, before.distances)
    idx.add(db[:1])  # still grows; the new matrix is read-only too
    assert len(idx.matrix) == 51 and not idx.matrix.flags.writeable
    for k in (0, -3, 2.7, "3", True, None):
        with pytest.raises(DataError, match=rf"k must be an integer >= 1, got {k!r}"):
            idx.search(q, k)
    with pytest.raises(DataError, match="k must be an integer >= 1, got 0"):
        DescriptorIndex(8).search(q, 0)  # also on an empty index
    assert idx.search(q, np.int64(2)).indices.shape == (3, 2)
