"""A flat bag of binary words for place recognition over hundreds of keyframes.

Brute-force Hamming matching of one keyframe's 500 ORB descriptors against a database of 100 keyframes takes
~300 ms here; quantizing them to 512 words takes ~2 ms and scoring a keyframe against the whole database is a
dense (K, W) operation. Words are k-majority centres (Grana et al., "A fast approach for integrating ORB
descriptors in the bag of words model", 2013): assign each descriptor to its nearest centre in Hamming
distance,
then set each centre bit to the majority of its members' bits. Vectors are tf-idf weighted and scored with
DBoW2's L1 score ``s(a, b) = 1 - 0.5 |a/|a|_1 - b/|b|_1|_1`` in [0, 1] (Galvez-Lopez and Tardos, 2012).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from scipy import sparse

DESCRIPTOR_BYTES = 32
"""Bytes of one ORB descriptor (256 bits)."""

VOCABULARY_FILE = Path(__file__).with_name("orb_vocabulary.npz")
"""The shipped vocabulary (``vocabulary`` key, shape (512, 32) uint8)."""


def train_vocabulary(descriptors: np.ndarray, n_words: int, iterations: int, seed: int) -> np.ndarray:
    """k-majority clustering of binary descriptors (vectorized: ~0.1 s for 10k descriptors, 512 words).

    Args:
        descriptors: ORB descriptors, shape (N, 32) uint8.
        n_words: Words wanted; fewer when N is smaller.
        iterations: Assignment/majority iterations.
        seed: Seed of the initial centres (drawn without replacement from the descriptors).

    Returns:
        Vocabulary, shape (W, 32) uint8.
    """
    descriptors = np.ascontiguousarray(descriptors, dtype=np.uint8)
    rng = np.random.default_rng(seed)
    n_words = min(n_words, len(descriptors))
    centres = descriptors[rng.choice(len(descriptors), n_words, replace=False)].copy()
    bits = np.unpackbits(descriptors, axis=1).astype(np.float32)
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    for _ in range(iterations):
        word = _nearest(matcher, descriptors, centres)
        counts = np.bincount(word, minlength=n_words)
        one_hot = sparse.csr_matrix(
            (np.ones(len(word), dtype=np.float32), (word, np.arange(len(word)))), shape=(n_words, len(word))
        )
        sums = np.asarray(one_hot @ bits)
        filled = counts > 0
        centres[filled] = np.packbits(2 * sums[filled] > counts[filled, None], axis=1)
        empty = np.flatnonzero(~filled)
        if len(empty):  # re-seed empty words with random descriptors
            centres[empty] = descriptors[rng.choice(len(descriptors), len(empty), replace=False)]
    return centres


def shipped_vocabulary() -> np.ndarray | None:
    """The vocabulary shipped with the package (``vio/loop/orb_vocabulary.npz``), or None when absent.

    Trained once (:func:`train_vocabulary`, 512 words) on ORB descriptors of rendered frames of the project's
    scenes (textured room, pillars, dark room) and of the EuRoC V1_01 micro set, so a run never stalls to
    train one and two runs share their words (a saved map stays valid).
    """
    if not VOCABULARY_FILE.is_file():
        return None
    with np.load(VOCABULARY_FILE) as z:
        return np.ascontiguousarray(z["vocabulary"], dtype=np.uint8)


def _nearest(matcher: cv2.BFMatcher, descriptors: np.ndarray, centres: np.ndarray) -> np.ndarray:
    matches = matcher.match(descriptors, centres)
    word = np.empty(len(descriptors), dtype=np.int64)
    word[[m.queryIdx for m in matches]] = [m.trainIdx for m in matches]
    return word


class BowDatabase:
    """Term-frequency vectors of keyframes, scored against a query with idf weights of the database.

    Args:
        vocabulary: Words, shape (W, 32) uint8.
    """

    def __init__(self, vocabulary: np.ndarray) -> None:
        """Empty database over ``vocabulary``."""
        self.vocabulary = np.ascontiguousarray(vocabulary, dtype=np.uint8)
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
        self._tf = np.zeros((0, len(self.vocabulary)), dtype=np.float32)
        self._n = 0
        self._doc_freq = np.zeros(len(self.vocabulary), dtype=np.int64)

    @property
    def n_words(self) -> int:
        """Words in the vocabulary."""
        return len(self.vocabulary)

    def __len__(self) -> int:
        """Vectors in the database."""
        return self._n

    def transform(self, descriptors: np.ndarray) -> np.ndarray:
        """Term frequencies of one image's descriptors, shape (N, 32) -> (W,) float32 summing to 1."""
        tf = np.zeros(self.n_words, dtype=np.float32)
        if len(descriptors) == 0:
            return tf
        word = _nearest(self._matcher, np.ascontiguousarray(descriptors, dtype=np.uint8), self.vocabulary)
        np.add.at(tf, word, 1.0)
        return tf / tf.sum()

    def add(self, tf: np.ndarray) -> int:
        """Append a vector; returns its row."""
        if self._n == len(self._tf):
            grown = np.zeros((max(16, 2 * len(self._tf)), self.n_words), dtype=np.float32)
            grown[: self._n] = self._tf[: self._n]
            self._tf = grown
        self._tf[self._n] = tf
        self._doc_freq += tf > 0
        self._n += 1
        return self._n - 1

    def scores(self, tf: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """L1 scores (0..1) of a query against database ``rows``, shape (R,)."""
        if len(rows) == 0:
            return np.zeros(0)
        idf = np.log(max(self._n, 1) / np.maximum(self._doc_freq, 1)).astype(np.float32)
        q = tf * idf
        db = self._tf[rows] * idf
        q = q / max(float(q.sum()), 1e-12)
        db = db / np.maximum(db.sum(axis=1, keepdims=True), 1e-12)
        return 1.0 - 0.5 * np.abs(db - q).sum(axis=1)
