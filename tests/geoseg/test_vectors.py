"""vector_length: the fast channel-axis norm used by the data pipeline, losses and metrics."""

import pytest
import torch

from geoseg.vectors import vector_length


@pytest.mark.parametrize("dim", [0, 1, -3, -1])
def test_vector_length_equals_torch_norm(dim):
    x = torch.randn(2, 3, 5, 7, dtype=torch.float64)
    expected = torch.linalg.vector_norm(x, dim=dim, keepdim=True)
    torch.testing.assert_close(vector_length(x, dim, keepdim=True), expected)
    torch.testing.assert_close(vector_length(x, dim), expected.squeeze(dim))


def test_vector_length_of_unit_normals_is_one_and_zero_stays_zero():
    n = torch.nn.functional.normalize(torch.randn(3, 4, 4), dim=0)
    n[:, 0, 0] = 0.0
    length = vector_length(n, 0)
    assert length[0, 0] == 0.0
    torch.testing.assert_close(length[1:], torch.ones(3, 4))
