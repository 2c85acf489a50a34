"""Sum-of-sines camera paths (d2gs_np/data/camera_paths.py)."""
import numpy as np
import pytest

from d2gs_np.data.camera_paths import as_times, eval_sines, random_sines

# eval_sines against a plain loop over the same terms: einsum sums n <= 3 products of O(0.1)
# values in another order, so they differ by a few ulps (~1e-17); 1e-15 still catches a wrong term.
ATOL = 1e-15


def test_a_block_holds_the_amplitudes_jittered_frequencies_and_phases():
    rng = np.random.default_rng(0)
    block = random_sines(rng, [[0.1, 0.2, 0.3], [0.01, 0.02, 0.03]], [1.0, 5.0], freq_jitter=0.15)
    assert block.shape == (2, 3, 3)
    np.testing.assert_array_equal(block[:, 0], [[0.1, 0.2, 0.3], [0.01, 0.02, 0.03]])
    f = block[:, 1] / np.array([1.0, 5.0])[:, None]
    assert np.all((f >= 0.85) & (f <= 1.15)) and not np.all(f == 1.0)
    assert np.all((block[:, 2] >= 0.0) & (block[:, 2] < 2.0 * np.pi))
    one_amp = random_sines(np.random.default_rng(0), [0.5, 0.5, 0.5], [2.0])  # amplitudes broadcast
    np.testing.assert_array_equal(one_amp[:, 0], [[0.5, 0.5, 0.5]])


def test_eval_sines_is_the_sum_of_its_terms():
    block = random_sines(np.random.default_rng(1), [[0.1, 0.2, 0.3], [0.05, 0.0, 0.02]], [0.7, 3.0])
    t = np.linspace(-0.1, 1.1, 13)
    want = np.zeros((t.size, 3))
    for n in range(block.shape[0]):
        for d in range(3):
            a, f, p = block[n, :, d]
            want[:, d] += a * np.sin(2.0 * np.pi * f * t + p)
    np.testing.assert_allclose(eval_sines(block, t), want, rtol=0, atol=ATOL)


def test_as_times_keeps_scalars_and_vectors_and_rejects_the_rest():
    assert as_times(0.25).shape == ()
    np.testing.assert_array_equal(as_times([0.0, 0.5]), [0.0, 0.5])
    with pytest.raises(ValueError, match="scalar or a 1-D array"):
        as_times(np.zeros((2, 2)))
    with pytest.raises(ValueError, match="times contains NaN or inf"):
        as_times([0.0, np.nan], name="times")
