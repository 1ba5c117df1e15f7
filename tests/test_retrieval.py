"""geoloc.retrieval.DescriptorIndex against a numpy brute force."""

from __future__ import annotations

import numpy as np
import pytest

import geoloc
from geoloc.retrieval import DescriptorIndex


def _brute(data: np.ndarray, q: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    d2 = ((q[:, None, :].astype(np.float64) - data[None].astype(np.float64)) ** 2).sum(-1)
    order = np.lexsort((np.broadcast_to(np.arange(len(data)), d2.shape), d2), axis=-1)[:, :k]
    return np.sqrt(np.take_along_axis(d2, order, 1)), order


@pytest.mark.parametrize("dim", [2, 3, 8, 16, 32, 128])
@pytest.mark.parametrize("backend", [None, "flat"])
def test_equals_brute_force(dim: int, backend: str | None) -> None:
    rng = np.random.default_rng(dim)
    data = rng.normal(size=(2000, dim)).astype(np.float32)
    data /= np.linalg.norm(data, axis=1, keepdims=True)
    q = rng.normal(size=(50, dim)).astype(np.float32)
    idx = DescriptorIndex(data, backend=backend)  # type: ignore[arg-type]
    assert idx.backend == (backend or ("kdtree" if dim <= 8 else "flat"))
    dist, ind = idx.query(q, k=4)
    want_d, want_i = _brute(data, q, 4)
    np.testing.assert_array_equal(ind, want_i)
    np.testing.assert_allclose(dist, want_d, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("dim", [3, 32])
def test_duplicated_descriptors_do_not_panic_and_tie_by_index(dim: int) -> None:
    data = np.ones((3000, dim), dtype=np.float32)
    data[2500:] = 2.0
    idx = DescriptorIndex(data)
    dist, ind = idx.query(np.ones(dim), k=3)
    np.testing.assert_array_equal(ind, [[0, 1, 2]])
    np.testing.assert_array_equal(dist, [[0, 0, 0]])
    _, ind = idx.query(np.full(dim, 2.0), k=1)
    assert ind[0, 0] == 2500


def test_bad_input() -> None:
    with pytest.raises(geoloc.InvalidInputError, match=r"descriptors: expected shape \(N, D\)"):
        DescriptorIndex(np.zeros(5))
    with pytest.raises(geoloc.InvalidInputError, match="non-empty"):
        DescriptorIndex(np.zeros((0, 4)))
    with pytest.raises(geoloc.InvalidInputError, match=r"descriptors\[1\] is not finite"):
        DescriptorIndex(np.array([[0.0, 1.0], [np.nan, 0.0]]))
    with pytest.raises(geoloc.InvalidInputError, match="backend"):
        DescriptorIndex(np.zeros((3, 4)), backend="ball")  # type: ignore[arg-type]
    with pytest.raises(geoloc.InvalidInputError, match="backend: the k-d tree serves"):
        DescriptorIndex(np.zeros((3, 40)), backend="kdtree")
    idx = DescriptorIndex(np.eye(4))
    with pytest.raises(geoloc.InvalidInputError, match=r"queries: expected shape \(N, 4\)"):
        idx.query(np.zeros((2, 3)))
    with pytest.raises(geoloc.InvalidInputError, match="k: expected an integer in 1..4"):
        idx.query(np.zeros(4), k=5)
    assert len(idx) == 4 and idx.dim == 4


@pytest.mark.parametrize("binary", [False, True])
def test_bow_retrieves_noisy_redraws_of_each_image(binary: bool) -> None:
    from geoloc.retrieval import BowDatabase, Vocabulary

    rng = np.random.default_rng(3)
    protos = rng.normal(size=(60, 32)) * 3
    layout = [[(i * 3 + j * 7) % 60 for j in range(6)] for i in range(20)]

    def draw(ids: list[int]) -> np.ndarray:
        d = np.repeat(protos[ids], 10, axis=0) + 0.3 * rng.normal(size=(60, 32))
        return np.packbits(d > 0, axis=1) if binary else d.astype(np.float32)

    images = [draw(ids) for ids in layout]
    vocab = Vocabulary.train(np.vstack(images), branching=8, depth=2, seed=1)
    db = BowDatabase(vocab, images)
    hits = sum(int(db.query(draw(ids), k=3)[1][0] == i) for i, ids in enumerate(layout))
    assert hits >= 18
    scores, ids = db.query(images[4], k=20)
    assert ids[0] == 4 and scores[0] == pytest.approx(1.0, abs=1e-5)
    assert np.all(np.diff(scores) <= 0)


@pytest.mark.parametrize("binary", [False, True])
def test_bow_scores_match_a_numpy_tfidf_per_descriptor_kind(binary: bool) -> None:
    """Scores against a dense numpy TF-IDF with DBoW2's L1 score: tf = the count for binary
    descriptors (ORB), tf = presence for float ones (SIFT; bursts of one word, repetitive
    texture, must not dominate), on bursty images where the two differ."""
    from geoloc.retrieval import BowDatabase, Vocabulary

    rng = np.random.default_rng(8)
    protos = rng.normal(size=(40, 32)) * 3

    def draw(ids: list[int]) -> np.ndarray:
        d = protos[ids] + 0.2 * rng.normal(size=(len(ids), 32))
        return np.packbits(d > 0, axis=1) if binary else d.astype(np.float32)

    # each image: 12 prototypes once, one of them repeated 25 more times (a burst)
    layout = [list(rng.choice(40, 12, replace=False)) for _ in range(15)]
    images = [draw(ids + [ids[0]] * 25) for ids in layout]
    vocab = Vocabulary.train(np.vstack(images), branching=8, depth=2, seed=2)
    db = BowDatabase(vocab, images)
    counts = np.zeros((len(images), len(vocab)))
    for i, im in enumerate(images):
        np.add.at(counts[i], vocab.words(im).astype(np.int64), 1)
    df = (counts > 0).sum(0)
    idf = np.where(df > 0, np.log(len(images) / np.maximum(df, 1)), 0.0)

    def score(q: np.ndarray, c: np.ndarray, presence: bool) -> float:
        vq, vc = ((q > 0) if presence else q) * idf, ((c > 0) if presence else c) * idf
        return float(np.minimum(vq / vq.sum(), vc / vc.sum()).sum())

    query = draw(layout[3][:8] + [layout[3][0]] * 10 + layout[7][:4])
    qc = np.zeros(len(vocab))
    np.add.at(qc, vocab.words(query).astype(np.int64), 1)
    want = np.array([score(qc, c, presence=not binary) for c in counts])
    scores, ids = db.query(query, k=len(images))
    np.testing.assert_allclose(scores, want[ids], atol=1e-6)
    # the other kind's weighting gives other scores here (the test can tell them apart)
    other = np.array([score(qc, c, presence=binary) for c in counts])
    assert np.abs(other - want).max() > 1e-3


def test_bow_bad_input() -> None:
    from geoloc.retrieval import BowDatabase, Vocabulary

    with pytest.raises(geoloc.InvalidInputError, match="cannot make 4 clusters"):
        Vocabulary.train(np.zeros((2, 8), dtype=np.float32), branching=4)
    vocab = Vocabulary.train(np.random.default_rng(0).normal(size=(100, 8)), branching=4, depth=2)
    with pytest.raises(geoloc.InvalidInputError, match="the vocabulary is for float descriptors of width 8"):
        vocab.words(np.zeros((3, 8), dtype=np.uint8))
    with pytest.raises(geoloc.InvalidInputError, match="vocabulary: expected"):
        BowDatabase("vocab", [])  # type: ignore[arg-type]


@pytest.mark.parametrize("scale", [1e20, 1e-25])
@pytest.mark.parametrize("backend", ["kdtree", "flat"])
def test_exact_at_extreme_magnitudes(scale: float, backend: str) -> None:
    """DescriptorIndex(x).query(x[[7, 42]]) with values near 1e20 returned index 0,
    distance 0 (inf - inf = NaN); now equal to brute force in float64."""
    rng = np.random.default_rng(1)
    x = (rng.normal(size=(100, 4)) * scale).astype(np.float32)
    q = np.vstack([x[[7, 42]], (rng.normal(size=(1, 4)) * scale).astype(np.float32)])
    dist, ind = DescriptorIndex(x, backend=backend).query(q, k=3)  # type: ignore[arg-type]
    d64 = np.linalg.norm(x.astype(np.float64)[None] - q.astype(np.float64)[:, None], axis=2)
    want = np.argsort(d64, axis=1, kind="stable")[:, :3]
    assert ind[:, 0].tolist()[:2] == [7, 42]
    np.testing.assert_array_equal(ind, want)
    np.testing.assert_allclose(dist, np.take_along_axis(d64, want, axis=1), rtol=1e-6)


def test_vocabulary_limits_are_named_errors() -> None:
    """Depth 20000 overflowed the stack (segfault); counts that do not fit raise
    InvalidInputError naming the argument (not OverflowError); numpy integers are accepted."""
    from geoloc.retrieval import Vocabulary

    zeros = np.zeros((50, 32), np.uint8)
    with pytest.raises(geoloc.InvalidInputError, match=r"^depth: "):
        Vocabulary.train(zeros, 2, 20000)
    with pytest.raises(geoloc.InvalidInputError, match=r"^branching: "):
        Vocabulary.train(zeros, -1, 2)
    with pytest.raises(geoloc.InvalidInputError, match=r"^seed: "):
        Vocabulary.train(zeros, 2, 2, seed=2**70)
    with pytest.raises(geoloc.InvalidInputError, match=r"^branching: "):
        Vocabulary.train(zeros, 2.5, 2)  # type: ignore[arg-type]
    assert len(Vocabulary.train(zeros, np.int64(2), np.uint8(24), seed=np.int64(3))) >= 1


def test_bow_scores_stay_in_unit_interval() -> None:
    """BoW scores reached 1.0000011 (f32 sums); now clamped f64 sums in [0, 1]."""
    from geoloc.retrieval import BowDatabase, Vocabulary

    rng = np.random.default_rng(7)
    images = [rng.integers(0, 256, (300, 32), dtype=np.uint8) for _ in range(30)]
    vocab = Vocabulary.train(np.vstack(images), branching=10, depth=3)
    db = BowDatabase(vocab, images)
    for im in images:
        scores, ids = db.query(im, k=30)
        assert np.all((scores >= 0) & (scores <= 1)), scores.max()


def test_bow_ties_rank_by_index() -> None:
    """A stopped camera: identical images score exactly alike and rank by index."""
    from geoloc.retrieval import BowDatabase, Vocabulary

    rng = np.random.default_rng(8)
    same = rng.integers(0, 256, (200, 32), dtype=np.uint8)
    images = [rng.integers(0, 256, (200, 32), dtype=np.uint8) for _ in range(5)] + [same] * 4
    db = BowDatabase(Vocabulary.train(np.vstack(images), branching=8, depth=2), images)
    scores, ids = db.query(same, k=4)
    assert ids.tolist() == [5, 6, 7, 8] and len(set(scores.tolist())) == 1
