import numpy as np
import pytest

from radarslam.errors import DataError
from radarslam.place_recognition.config import ImageConfig
from radarslam.place_recognition.image import (
    normalise_rcs,
    pack_images,
    pixel_indices,
    rasterise,
    unpack_images,
)


def test_exact_pixel_of_points():
    cfg = ImageConfig()
    xy = np.array([[0.0, 0.0], [10.2, -3.7], [-5.5, 0.49], [99.4, 99.4], [-100.0, -100.0]])
    img = rasterise(xy, cfg)
    assert img.shape == (1, 200, 200) and img.dtype == np.uint8
    # rows = x, cols = y, round half up, +100
    expected = {(100, 100), (110, 96), (95, 100), (199, 199), (0, 0)}
    assert set(zip(*np.nonzero(img[0]), strict=True)) == expected
    assert img.sum() == len(expected)


def test_crop_and_bounds():
    cfg = ImageConfig()
    xy = np.array([[99.5, 0.0], [0.0, 99.6], [-100.6, 0.0], [-100.4, 5.0], [150.0, 1.0]])
    _, _, keep = pixel_indices(xy, cfg)
    # 99.5 rounds to 100 -> row 200, outside; -100.4 rounds to -100 but is beyond the 100 m crop
    assert keep.tolist() == [False, False, False, False, False]
    small = ImageConfig(size_px=20, resolution_m=2.0, crop_m=15.0)
    img = rasterise(np.array([[3.0, -3.0], [14.0, 0.0], [16.0, 0.0]]), small)
    # 3/2 + 0.5 = 2.0 -> 2 + 10 = 12 ; -3/2 + 0.5 = -1 -> 9 ; 14/2 -> 17 ; 16 m is cropped
    assert set(zip(*np.nonzero(img[0]), strict=True)) == {(12, 9), (17, 10)}


def test_extra_channels_and_rcs_normalisation():
    cfg = ImageConfig(size_px=10, extra_channels=["count", "rcs"], count_saturation=4)
    xy = np.array([[0.1, 0.1], [0.2, -0.2], [0.0, 0.3], [2.0, 2.0]])
    rcs01 = normalise_rcs(np.array([-5.0, 5.0, 0.0, 15.0]))
    np.testing.assert_allclose(rcs01, [0.0, 0.5, 0.25, 1.0])
    img = rasterise(xy, cfg, rcs01)
    assert img.shape == (3, 10, 10)
    assert img[0, 5, 5] == 1 and img[1, 5, 5] == round(3 / 4 * 255) and img[2, 5, 5] == 128
    assert img[1, 7, 7] == round(255 / 4) and img[2, 7, 7] == 255
    with pytest.raises(DataError):
        rasterise(xy, cfg)  # rcs channel without values
    assert normalise_rcs(np.array([3.0, 3.0])).tolist() == [0.0, 0.0]


def test_pack_roundtrip_and_bad_input():
    rng = np.random.default_rng(0)
    imgs = (rng.random((3, 200, 200)) < 0.05).astype(np.uint8)
    packed = pack_images(imgs)
    assert packed.shape == (3, 200, 25)
    np.testing.assert_array_equal(unpack_images(packed, 200), imgs)
    with pytest.raises(DataError, match="NaN"):
        rasterise(np.array([[np.nan, 0.0]]), ImageConfig())
    with pytest.raises(DataError, match="shape"):
        rasterise(np.zeros(5), ImageConfig())
