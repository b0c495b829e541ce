"""The instruction encoder: an embedding depends on its text alone, never on what it was
encoded beside or on what the cache held before (a run's numbers must not hang on its history)."""

import numpy as np

from policies import text_encoder
from policies.text_encoder import embed_instructions

SHORT = "open the drawer"
MIDDLE = "pick up the puck and place it at the goal"
LONG = ("pick up the black bowl between the plate and the ramekin and place it on the plate "
        "in the kitchen scene")


def test_embedding_does_not_depend_on_its_batch():
    alone = embed_instructions([MIDDLE])[0]
    beside_longer = embed_instructions([LONG, MIDDLE, SHORT])[1]
    assert np.array_equal(alone, beside_longer)  # a batch padded to LONG moved it by ~1e-7
    assert np.isclose(np.linalg.norm(alone), 1.0, atol=1e-5)


def test_cached_embedding_is_the_same_whichever_run_filled_the_cache(tmp_path, monkeypatch):
    first = embed_instructions([LONG, MIDDLE], tmp_path / "a")
    second = embed_instructions([MIDDLE, SHORT], tmp_path / "b")
    assert np.array_equal(first[1], second[0])

    def no_encoder():
        raise AssertionError("the cached embedding should have been read, not recomputed")

    monkeypatch.setattr(text_encoder, "_model", no_encoder)
    again = embed_instructions([SHORT, MIDDLE], tmp_path / "b")
    assert np.array_equal(again, second[::-1])
