import numpy as np
import pytest

from place_recognition.config import RetrievalConfig
from place_recognition.retrieval import DescriptorIndex
from radarslam.errors import DataError


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
