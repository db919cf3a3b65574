"""The refiner-bounds benchmark compares like with like: every layout computes the decoder's pooled
features, and every kNN search finds neighbours at the same distances."""

from __future__ import annotations

import numpy as np
import torch

from benchmarks.generation.refiner_bounds import BRUTE_QUERIES, knn_searches, pooled_channels_last
from datagen.pipeline.refine.poco.network import PocoModel


def test_channels_last_layout_computes_the_pipelines_pooled_features() -> None:
    torch.manual_seed(0)
    model = PocoModel("small").eval()
    decoder = model.projection
    latents, points, queries = torch.randn(1, 16, 300), torch.randn(1, 3, 300), torch.randn(1, 3, 200)
    with torch.inference_mode():
        terms = decoder.point_terms(latents, points)
        index = model.query_knn(points, queries)
        query_terms = decoder.query_terms(queries)
        want = decoder.pooled_inference(terms, query_terms, index)[0].T
        got = pooled_channels_last(decoder, terms[0].T.contiguous(), query_terms[0].T.contiguous(), index)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)


def test_every_knn_search_finds_the_same_distances() -> None:
    rng = np.random.default_rng(1)
    source = rng.integers(0, 30, size=(500, 3)).astype(np.float64)  # a grid: many tied distances
    targets = rng.integers(0, 30, size=(min(300, BRUTE_QUERIES), 3)).astype(np.float64)
    truth = np.sort(((targets[:, None] - source[None]) ** 2).sum(axis=2), axis=1)[:, :8]
    for name, search in knn_searches(8).items():
        found = np.asarray(search(source, targets))
        distances = np.sort(((targets[:, None] - source[found]) ** 2).sum(axis=2), axis=1)
        np.testing.assert_array_equal(distances, truth, err_msg=name)
