"""LeRobot datasets in and out, without lerobot itself (it does not install beside our pins):
pyarrow reads and writes the parquet files, PyAV decodes and encodes the images and videos.

- `layout`: a dataset folder of format v2.0, v2.1 or v3.0 (its info.json, tasks, episodes).
- `frames`: PyAV decoding (PNG bytes, mp4 segments) and encoding (PNG, AV1 video).
- `reader`: a benchmark's tasks' episodes from a folder given as `demos_dir`.
- `writer`: episodes as a v3.0 folder that LeRobot 0.4 and later load.

The commands built on them live higher up: `harness.run.lerobot_export` (`make lerobot-export`,
a benchmark's demos out) and `harness.perf.lerobot` (the reader's speed, the export-and-read-back
identity check).

Every malformed input is a RetainError of one line naming the file and what was expected.
"""
