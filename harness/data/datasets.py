"""Demonstrations as training samples: one (observation, action chunk) pair per demo step.

A chunk holds the next `chunk_size` actions; past an episode's end it repeats the last action
and masks the padding out of the loss (as LeRobot does).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from harness.data.demos import Episode


@dataclass
class TrainingData:
    """Samples of one or more tasks, held as tensors. `task_names[task_index[i]]` is sample i's task."""

    obs: dict[str, torch.Tensor]  # key -> [N, ...]
    actions: torch.Tensor  # [N, H, A]
    action_mask: torch.Tensor  # [N, H] bool
    task_index: torch.Tensor  # [N] long
    instruction_table: torch.Tensor  # [T, 384] one row per task
    task_names: list[str]
    instruction_tokens: torch.Tensor | None = None  # [T, L] MiniLM token ids per task (0 = pad)
    # [T] each task's index into the benchmark's instruction texts (cfg.all_tasks() order), for
    # policies that tokenize the text themselves (LeRobot's)
    instruction_ids: torch.Tensor | None = None

    def __len__(self) -> int:
        return len(self.actions)

    def batch(self, idx: torch.Tensor) -> dict[str, torch.Tensor]:
        out = {k: v[idx] for k, v in self.obs.items()}
        out["actions"] = self.actions[idx]
        out["action_mask"] = self.action_mask[idx]
        out["instruction"] = self.instruction_table[self.task_index[idx]]
        out["task_index"] = self.task_index[idx]
        out["index"] = idx
        if self.instruction_tokens is not None:
            out["instruction_tokens"] = self.instruction_tokens[out["task_index"]]
        if self.instruction_ids is not None:
            out["instruction_id"] = self.instruction_ids[out["task_index"]]
        return out

    def sample(self, batch_size: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
        return self.batch(torch.randint(len(self), (batch_size,), generator=generator))

    def subset(self, idx: torch.Tensor) -> TrainingData:
        return TrainingData({k: v[idx] for k, v in self.obs.items()}, self.actions[idx],
                            self.action_mask[idx], self.task_index[idx], self.instruction_table,
                            self.task_names, self.instruction_tokens, self.instruction_ids)

    def to(self, device: torch.device | str) -> TrainingData:
        """The same samples with every tensor on `device` (itself when already there)."""
        if self.actions.device == torch.device(device):
            return self
        return TrainingData({k: v.to(device) for k, v in self.obs.items()},
                            self.actions.to(device), self.action_mask.to(device),
                            self.task_index.to(device), self.instruction_table.to(device),
                            self.task_names, None if self.instruction_tokens is None
                            else self.instruction_tokens.to(device),
                            None if self.instruction_ids is None
                            else self.instruction_ids.to(device))

    def for_task(self, task: str) -> TrainingData:
        return self.subset(torch.nonzero(self.task_index == self.task_names.index(task)).flatten())

    def random_subset(self, n: int, generator: torch.Generator) -> TrainingData:
        """At most `n` samples drawn without replacement."""
        return self.subset(torch.randperm(len(self), generator=generator)[:n])

    def per_task_subset(self, n: int, generator: torch.Generator) -> TrainingData:
        """At most `n` samples of each task, drawn without replacement: what a replay buffer or
        an episodic memory keeps of a finished stage."""
        return TrainingData.concat([self.for_task(t).random_subset(n, generator)
                                    for t in self.task_names])

    @staticmethod
    def concat(parts: list[TrainingData]) -> TrainingData:
        """Join datasets, re-indexing tasks so every task name appears once. The result lives
        where the first part does (a memory kept on the CPU, a stage's data on a GPU)."""
        device = parts[0].actions.device
        parts = [p.to(device) for p in parts]
        names: list[str] = []
        rows: list[torch.Tensor] = []
        token_rows: list[torch.Tensor | None] = []
        id_rows: list[torch.Tensor | None] = []
        for part in parts:
            for i, name in enumerate(part.task_names):
                if name not in names:
                    names.append(name)
                    rows.append(part.instruction_table[i])
                    tokens, ids = part.instruction_tokens, part.instruction_ids
                    token_rows.append(None if tokens is None else tokens[i])
                    id_rows.append(None if ids is None else ids[i])
        has_tokens = bool(token_rows) and all(r is not None for r in token_rows)
        if has_tokens:  # padded (id 0) to the longest
            width = max(len(r) for r in token_rows)
            token_rows = [torch.nn.functional.pad(r, (0, width - len(r))) for r in token_rows]
        remapped = [torch.tensor([names.index(n) for n in p.task_names], device=device)[p.task_index]
                    for p in parts]
        keys = parts[0].obs.keys()
        return TrainingData(
            {k: torch.cat([p.obs[k] for p in parts]) for k in keys},
            torch.cat([p.actions for p in parts]),
            torch.cat([p.action_mask for p in parts]),
            torch.cat(remapped),
            torch.stack(rows) if rows else parts[0].instruction_table[:0],
            names,
            torch.stack(token_rows) if has_tokens else None,
            torch.stack(id_rows) if id_rows and all(r is not None for r in id_rows) else None,
        )


def chunk_episodes(
    episodes: list[Episode], task: str, instruction_embedding: np.ndarray, chunk_size: int,
    instruction_tokens: np.ndarray | None = None, instruction_id: int | None = None,
) -> TrainingData:
    obs_parts: dict[str, list[np.ndarray]] = {k: [] for k in episodes[0].obs}
    action_parts, mask_parts = [], []
    offsets = np.arange(chunk_size)
    for episode in episodes:
        t_len = len(episode)
        idx = np.arange(t_len)[:, None] + offsets[None]  # [T, H]
        mask_parts.append(idx < t_len)
        action_parts.append(episode.actions[np.minimum(idx, t_len - 1)])
        for k in obs_parts:
            obs_parts[k].append(episode.obs[k])
    n = sum(len(e) for e in episodes)
    return TrainingData(
        {k: torch.from_numpy(np.concatenate(v)) for k, v in obs_parts.items()},
        torch.from_numpy(np.concatenate(action_parts).astype(np.float32)),
        torch.from_numpy(np.concatenate(mask_parts)),
        torch.zeros(n, dtype=torch.long),
        torch.from_numpy(np.asarray(instruction_embedding, np.float32)[None]),
        [task],
        None if instruction_tokens is None
        else torch.from_numpy(np.asarray(instruction_tokens, np.int64)[None]),
        None if instruction_id is None else torch.tensor([instruction_id]),
    )


def instruction_entries(instructions: dict, tasks: list[str]) -> dict[str, torch.Tensor]:
    """The batch entries of the instructions of `tasks` (one per row): a task's value is its
    pooled embedding [384], or a dict of entries ({"instruction": [384],
    "instruction_tokens": [L]}) as `harness.data.prepare.prepare_data` makes."""
    values = [instructions[t] for t in tasks]
    if not isinstance(values[0], dict):
        return {"instruction": torch.as_tensor(np.stack(values))}
    return {k: torch.as_tensor(np.stack([v[k] for v in values])) for k in values[0]}


def batch_to(batch: dict, device: torch.device, non_blocking: bool = False) -> dict:
    """A batch's tensors on `device` (the others as they are): a batch drawn from data kept
    elsewhere (a CPU memory) for a policy on a GPU."""
    return {k: v.to(device, non_blocking=non_blocking) if torch.is_tensor(v) else v
            for k, v in batch.items()}


def merge_batches(*batches: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """One batch from several (same keys); "index" and "task_index" lose their meaning. The
    result lives where the first batch does (a replay buffer may be kept elsewhere)."""
    keys = [k for k in batches[0] if k not in ("index", "task_index")]
    return {k: torch.cat([b[k].to(batches[0][k].device) for b in batches]) for k in keys}
