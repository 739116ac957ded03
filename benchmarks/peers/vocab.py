"""A home-trained ORB vocabulary for ORB-SLAM3, in DBoW2's text format (the format of ``ORBvoc.txt``).

The published ``ORBvoc.txt`` (trained on a large image collection) is downloaded by ``pyorbslam3`` at run time,
which cannot be done here, and the package ships no training tool. This module trains one the way DBoW2's
``TemplatedVocabulary::create`` does: ORB descriptors (OpenCV's ORB, the same 256-bit rBRIEF pattern ORB-SLAM3's
extractor uses) of training images, hierarchical k-means++ with the Hamming distance and bitwise-majority
centres (DBoW2's ``FORB::meanValue``), ``k`` branches and ``L`` levels, words weighted by TF-IDF
(``log(N_images / n_images_with_word)``), L1 scoring. Results that use it must say so: it is not the
published vocabulary, and place recognition (relocalisation, loop closing) depends on it.

Text format read by ORB-SLAM3's ``loadFromTextFile``: a first line ``k L scoring weighting`` (``0 0``: L1 norm,
TF-IDF), then one line per node in id order (root excluded): ``parent_id is_leaf d0 ... d31 weight``; the file
must not end in an empty line (ORB-SLAM3 would read it as one more node).
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable
from pathlib import Path

import numpy as np

__all__ = ["orb_descriptors", "train_vocabulary", "write_dbow2_text", "read_dbow2_text", "transform"]


def orb_descriptors(images: Iterable[np.ndarray], n_features: int = 1000) -> list[np.ndarray]:
    """ORB descriptors of each grey image: a list of (n_i, 32) uint8 arrays (8 levels, scale 1.2, as
    ORB-SLAM3's EuRoC settings)."""
    import cv2

    orb = cv2.ORB_create(nfeatures=n_features, scaleFactor=1.2, nlevels=8, edgeThreshold=19, patchSize=31)
    out = []
    for img in images:
        _, des = orb.detectAndCompute(img, None)
        out.append(np.zeros((0, 32), np.uint8) if des is None else des)
    return out


def _hamming(bits: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(n, m) Hamming distances between (n, 256) and (m, 256) 0/1 float32 bit arrays."""
    a = bits.sum(1, keepdims=True)
    b = centres.sum(1)[None, :]
    return a + b - 2.0 * (bits @ centres.T)


def _kmeans(bits: np.ndarray, k: int, rng: np.random.Generator, iters: int = 10) -> np.ndarray:
    """k-means++ seeding and Lloyd iterations with bitwise-majority centres; returns labels (n,)."""
    n = bits.shape[0]
    centres = [bits[rng.integers(n)]]
    d = _hamming(bits, centres[0][None])[:, 0]
    for _ in range(1, k):
        p = d**2
        s = p.sum()
        idx = rng.integers(n) if s <= 0 else rng.choice(n, p=p / s)
        centres.append(bits[idx])
        d = np.minimum(d, _hamming(bits, bits[idx][None])[:, 0])
    C = np.stack(centres)
    labels = np.full(n, -1)
    for _ in range(iters):
        new = np.argmin(_hamming(bits, C), axis=1)
        if np.array_equal(new, labels):
            break
        labels = new
        for j in range(k):
            m = labels == j
            if m.any():
                C[j] = (bits[m].mean(0) >= 0.5).astype(np.float32)
    return labels


def train_vocabulary(descriptors: list[np.ndarray], k: int = 10, L: int = 5, seed: int = 0) -> dict:
    """Train a DBoW2 vocabulary tree from per-image descriptors ((n_i, 32) uint8 each).

    Returns ``{"k", "L", "parent": (N,), "leaf": (N,) bool, "desc": (N, 32) uint8, "weight": (N,)}`` for nodes
    1..N in DBoW2's id order (breadth-first: the children of a node get consecutive ids).
    """
    rng = np.random.default_rng(seed)
    all_des = np.concatenate([d for d in descriptors if len(d)], axis=0)
    img_of = np.concatenate([np.full(len(d), i) for i, d in enumerate(descriptors) if len(d)])
    if all_des.shape[0] < k:
        raise ValueError(f"only {all_des.shape[0]} descriptors to train a vocabulary with k={k}")
    bits = np.unpackbits(all_des, axis=1).astype(np.float32)
    parent, leaf, desc, members = [], [], [], []
    queue = [(0, np.arange(all_des.shape[0]), 1)]  # (node id, descriptor indices, level of its children)
    while queue:
        nid, idx, level = queue.pop(0)
        if idx.size <= k:  # DBoW2: fewer descriptors than branches -> each one is a child (a cluster of its own)
            groups = [idx[j : j + 1] for j in range(idx.size)]
        else:
            lab = _kmeans(bits[idx], k, rng)
            groups = [idx[lab == j] for j in range(k) if (lab == j).any()]
        for g in groups:
            cid = len(parent) + 1
            parent.append(nid)
            centre = (bits[g].mean(0) >= 0.5).astype(np.uint8)
            desc.append(np.packbits(centre))
            is_leaf = level >= L or g.size <= 1
            leaf.append(is_leaf)
            members.append(g)
            if not is_leaf:
                queue.append((cid, g, level + 1))
    n_img = len(descriptors)
    weight = np.zeros(len(parent))
    for j, (is_leaf, g) in enumerate(zip(leaf, members, strict=True)):
        if is_leaf:
            ni = np.unique(img_of[g]).size
            weight[j] = np.log(n_img / ni) if ni else 0.0
    return {
        "k": k,
        "L": L,
        "parent": np.asarray(parent, dtype=np.int64),
        "leaf": np.asarray(leaf, dtype=bool),
        "desc": np.asarray(desc, dtype=np.uint8).reshape(-1, 32),
        "weight": weight,
    }


def write_dbow2_text(voc: dict, path: str | Path) -> Path:
    """Write ``voc`` in DBoW2's text format (no trailing newline); returns ``path``."""
    lines = [f"{voc['k']} {voc['L']} 0 0"]
    for p, lf, d, w in zip(voc["parent"], voc["leaf"], voc["desc"], voc["weight"], strict=True):
        lines.append(f"{int(p)} {int(lf)} {' '.join(str(int(x)) for x in d)} {float(w):.6f}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".part")
    tmp.write_text("\n".join(lines))
    tmp.replace(path)
    return path


def read_dbow2_text(path: str | Path) -> dict:
    """Read a DBoW2 text vocabulary written by :func:`write_dbow2_text` (or ``ORBvoc.txt``)."""
    text = Path(path).read_text().split("\n")
    k, L, scoring, weighting = (int(x) for x in text[0].split())
    if not (0 < k <= 20 and 1 <= L <= 10 and 0 <= scoring <= 5 and 0 <= weighting <= 3):
        raise ValueError(f"{path}: not a DBoW2 text vocabulary (header {text[0]!r})")
    rows = [ln.split() for ln in text[1:] if ln.strip()]
    if any(len(r) != 35 for r in rows):
        raise ValueError(f"{path}: every node line must hold parent, leaf flag, 32 bytes and a weight")
    return {
        "k": k,
        "L": L,
        "parent": np.array([int(r[0]) for r in rows], dtype=np.int64),
        "leaf": np.array([int(r[1]) > 0 for r in rows]),
        "desc": np.array([[int(x) for x in r[2:34]] for r in rows], dtype=np.uint8).reshape(-1, 32),
        "weight": np.array([float(r[34]) for r in rows]),
    }


def transform(voc: dict, des: np.ndarray) -> np.ndarray:
    """Word index (0-based, in leaf order) of each descriptor, descending the tree by Hamming distance as
    DBoW2's ``transform`` does."""
    children: dict[int, list[int]] = {}
    for j, p in enumerate(voc["parent"]):
        children.setdefault(int(p), []).append(j + 1)
    word_of = np.full(len(voc["parent"]) + 1, -1)
    word_of[1:][voc["leaf"]] = np.arange(int(voc["leaf"].sum()))
    bits = np.unpackbits(voc["desc"], axis=1).astype(np.float32)
    q = np.unpackbits(np.asarray(des, np.uint8).reshape(-1, 32), axis=1).astype(np.float32)
    out = []
    for row in q:
        nid = 0
        while nid in children:
            ch = children[nid]
            nid = ch[int(np.argmin(_hamming(row[None], bits[np.array(ch) - 1])[0]))]
        out.append(word_of[nid])
    return np.asarray(out)


def fingerprint(descriptor_sets: list[np.ndarray], k: int, L: int, seed: int) -> str:
    """A short hash of the training data and parameters (the cache key of a trained vocabulary)."""
    h = hashlib.sha1(f"{k} {L} {seed}".encode())
    for d in descriptor_sets:
        h.update(np.ascontiguousarray(d).tobytes())
    return h.hexdigest()[:12]
