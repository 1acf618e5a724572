"""geometry.blur against cv2.GaussianBlur, its oracle: the same kernel and border, wide kernels included."""

import cv2
import numpy as np
import pytest

from panoworld.geometry.blur import blur_matrix, gaussian_blur, reflect101


@pytest.mark.parametrize("n", [1, 2, 5, 37, 724])
def test_reflect101_is_cv2_border_interpolate(n):
    p = np.arange(-4 * n - 9, 5 * n + 9)
    assert [int(q) for q in reflect101(p, n)] == [cv2.borderInterpolate(int(q), n, cv2.BORDER_REFLECT_101) for q in p]


@pytest.mark.parametrize("shape", [(96, 96), (96, 96, 3), (40, 130, 3), (7, 9)])
@pytest.mark.parametrize("sigma", [1.5, 9.0, 40.0, 170.0])
def test_gaussian_blur_equals_cv2(shape, sigma):
    """Narrow kernels go to cv2 itself; kernels wider than the image (reflected more than once) as matrix products."""
    x = np.random.default_rng(0).random(shape).astype(np.float32)
    x[: shape[0] // 3] *= 5.0  # a step: the border's reflections matter
    got = gaussian_blur(x, sigma)
    assert got.dtype == np.float32 and got.shape == x.shape
    np.testing.assert_allclose(got, cv2.GaussianBlur(x, (0, 0), sigma), rtol=0, atol=2e-5 * float(x.max()))


def test_blur_matrix_rows_sum_to_one():
    B = blur_matrix(50, 30.0, 241)
    np.testing.assert_allclose(B.sum(1), 1.0, atol=1e-5)
    assert not B.flags.writeable
