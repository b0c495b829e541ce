"""The report as one self-contained HTML page: the summary's tables and figures, and a grid of
rollout videos, task by stage, method beside method.

Self-contained: the figures and the videos are inside the page as data URIs, so it opens from
disk, from an MLflow artifact or from a mail, with nothing beside it. That makes it grow with
the videos (a 150-step Meta-World episode at 224 px: about 55 kB); the page takes one seed's videos
per row, its lowest seed that has them.
"""

from __future__ import annotations

import base64
import html
import re
from dataclasses import dataclass
from pathlib import Path

from markdown_it import MarkdownIt

from harness.common.atomic import write_text
from harness.evaluate.recording import VideoEntry, read_indexes

PAGE = "report.html"
STYLE = """
body{font-family:system-ui,sans-serif;margin:1.5em auto;max-width:1400px;padding:0 1em;color:#222}
table{border-collapse:collapse;font-size:.85em;margin:.8em 0}
th,td{border:1px solid #ccc;padding:.25em .5em;text-align:right}
th:first-child,td:first-child{text-align:left}
img{max-width:100%}
.task{border-top:1px solid #ddd;padding:.6em 0}
.stages{display:flex;gap:1.2em;flex-wrap:wrap;align-items:flex-start}
.stage h4{margin:.2em 0;font-weight:600;font-size:.9em}
.methods{display:flex;gap:.5em}
figure{margin:0;text-align:center;font-size:.8em}
video{display:block;background:#000;min-width:200px;cursor:pointer}
.success{color:#1a7f37}.failure{color:#c62828}
"""


@dataclass(frozen=True)
class RowVideos:
    """One report row's videos: those of its run at `seed`, in `directory`."""

    label: str
    seed: int
    directory: Path
    entries: list[VideoEntry]

    @classmethod
    def read(cls, label: str, seed: int, directory: Path) -> RowVideos:
        return cls(label, seed, Path(directory), read_indexes(directory))


def write_page(out: Path, benchmark: str, markdown_files: list[Path],
               foundation_tasks: list[str], stream_tasks: list[str],
               videos: list[RowVideos]) -> Path:
    """`out/report.html` from the report's Markdown files (figures embedded) and the videos."""
    md = MarkdownIt("commonmark").enable("table")
    parts = [f"<section id=\"{path.stem}\">{_embed(md.render(path.read_text()), path.parent)}"
             "</section>" for path in markdown_files]
    if any(v.entries for v in videos):
        parts.append(video_grid(foundation_tasks, stream_tasks, videos))
    page = (f"<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>{html.escape(benchmark)}: Retain report</title><style>{STYLE}</style>"
            f"</head><body>\n" + "\n<hr>\n".join(parts) + "\n</body></html>\n")
    path = out / PAGE
    write_text(path, page)
    return path


def video_grid(foundation_tasks: list[str], stream_tasks: list[str], videos: list[RowVideos]
               ) -> str:
    """Per task (foundation, then stream): stage 0 once (every method starts from the same
    foundation), then after the task's own stage and after the last, one video per method."""
    last = max((e.stage for v in videos for e in v.entries), default=0)
    lines = ["<h2 id=\"videos\">Rollout videos</h2>",
             "<p>The same evaluation episode (same initial state, same sampling noise) before "
             "fine-tuning, after the task's own stage and after the last stage, one video per "
             f"method (seed {', '.join(sorted({str(v.seed) for v in videos}))}). Under each: "
             "the instruction, the stage and, at the end, the outcome. Click a video for its "
             "controls.</p>"]
    for task in foundation_tasks + stream_tasks:
        cells = {(v.label, e.stage): [x for x in v.entries if x.task == task and x.stage == e.stage]
                 for v in videos for e in v.entries if e.task == task}
        if not cells:
            continue
        stages = sorted({stage for _, stage in cells})
        kind = "foundation task" if task in foundation_tasks else "stream task"
        instruction = next(e.instruction for v in videos for e in v.entries if e.task == task)
        lines.append(f"<div class=\"task\"><h3>{html.escape(task)} <small>({kind}: "
                     f"“{html.escape(instruction)}”)</small></h3><div class=\"stages\">")
        for stage in stages:
            rows = [v for v in videos if cells.get((v.label, stage))]
            if stage == 0:
                rows, title = rows[:1], "stage 0: the foundation (every method)"
            else:
                trained = cells[(rows[0].label, stage)][0].trained_on
                when = "after the last stage" if stage == last else "after its own stage"
                title = f"stage {stage} ({when}, trained on {trained})"
            lines.append(f"<div class=\"stage\"><h4>{html.escape(title)}</h4>"
                         "<div class=\"methods\">")
            for v in rows:
                for entry in cells[(v.label, stage)]:
                    name = "foundation" if stage == 0 else v.label
                    lines.append(_figure(v.directory / entry.file, name, entry))
            lines.append("</div></div>")
        lines.append("</div></div>")
    return "\n".join(lines)


def _figure(path: Path, name: str, entry: VideoEntry) -> str:
    outcome = "success" if entry.success else "failure"
    data = base64.b64encode(path.read_bytes()).decode()
    return (f"<figure><video autoplay muted loop playsinline preload=\"auto\" "
            f"onclick=\"this.controls=!this.controls\" "
            f"data-task=\"{html.escape(entry.task)}\" data-stage=\"{entry.stage}\" "
            f"src=\"data:video/mp4;base64,{data}\"></video><figcaption>{html.escape(name)}, "
            f"ep {entry.episode}: <span class=\"{outcome}\">{outcome}</span> "
            f"({entry.steps} steps)</figcaption></figure>")


def _embed(text: str, folder: Path) -> str:
    """Every `<img src="x.png">` of the report folder as a data URI; links to the report's
    Markdown files (paper_table.md) to the page's own sections."""
    def embed(found: re.Match) -> str:
        path = folder / found.group(1)
        if not path.is_file():
            return found.group(0)
        return f'src="data:image/png;base64,{base64.b64encode(path.read_bytes()).decode()}"'

    text = re.sub(r'href="([^"/:]+)\.md"', r'href="#\1"', text)
    return re.sub(r'src="([^"/:]+\.png)"', embed, text)
