"""Camera frames with PyAV, whose wheels bundle FFmpeg with an AV1 decoder (dav1d) and encoder
(SVT-AV1), so no system FFmpeg is needed: PNG bytes and mp4 segments decoded to uint8
[T, H, W, 3] RGB, and the writer's PNG and video encoders. Decoding failures raise FrameError
(a ValueError) with one line; the caller names the file."""

from __future__ import annotations

import os
from fractions import Fraction
from pathlib import Path

import numpy as np

os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1 prints a banner on every encoder without it

TIME_TOLERANCE = 1e-4  # s: how far a frame's time may be from its slot (LeRobot's tolerance_s)
VIDEO_CODEC, VIDEO_PIX_FMT = "libsvtav1", "yuv420p"  # LeRobot's defaults for its datasets
VIDEO_OPTIONS = {"crf": "30", "g": "2", "preset": "8"}  # crf and g as LeRobot's; g 2 seeks fast


class FrameError(ValueError):
    """An image or video that does not decode to the frames expected."""


def _why(err: Exception) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__


def decode_png(data: bytes) -> np.ndarray:
    """One PNG (LeRobot's `image` features) as uint8 [H, W, 3]."""
    import av

    # a fresh decoder per image: one reused across images returned earlier images (measured)
    codec = av.CodecContext.create("png", "r")
    try:
        frames = codec.decode(av.Packet(bytes(data))) + codec.decode(None)
    except av.error.FFmpegError as err:
        raise FrameError(f"not a readable PNG ({_why(err)})") from None
    if len(frames) != 1:
        raise FrameError(f"PNG bytes held {len(frames)} images; expected 1")
    return frames[0].to_ndarray(format="rgb24")


def decode_video(path: Path, start: float, count: int, fps: float) -> np.ndarray:
    """The `count` frames at `start`, `start + 1/fps`, ... seconds of an mp4 (an episode's
    segment of a v3.0 file, or a whole v2.x episode file) as uint8 [count, H, W, 3]. Every
    frame must sit on its slot within TIME_TOLERANCE, none missing, none extra."""
    import av

    frames: list[np.ndarray] = []
    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise FrameError("holds no video stream")
            stream = container.streams.video[0]
            stream.thread_type = "AUTO"
            if start > 0:  # to the key frame at or before the segment (LeRobot's g=2: near)
                container.seek(int(start / stream.time_base), stream=stream)
            for frame in container.decode(stream):
                if frame.time is None:
                    raise FrameError(f"frame {len(frames)} has no timestamp")
                offset = frame.time - start
                if offset < -TIME_TOLERANCE:
                    continue
                slot = round(offset * fps)
                if slot >= count:
                    break
                if abs(offset - slot / fps) > TIME_TOLERANCE or slot != len(frames):
                    raise FrameError(f"frame at {frame.time:.4f} s is not frame {len(frames)} "
                                     f"of the segment from {start:.4f} s at {fps:g} fps")
                frames.append(frame.to_ndarray(format="rgb24"))
    except av.error.FFmpegError as err:
        raise FrameError(f"not a readable video ({_why(err)})") from None
    if len(frames) != count:
        raise FrameError(f"holds {len(frames)} frames from {start:.4f} s; expected {count} "
                         f"at {fps:g} fps")
    return np.stack(frames)


def encode_png(image: np.ndarray) -> bytes:
    import av

    codec = av.CodecContext.create("png", "w")
    codec.height, codec.width = image.shape[:2]
    codec.pix_fmt = "rgb24"
    frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="rgb24")
    return b"".join(bytes(p) for p in codec.encode(frame) + codec.encode(None))


class VideoWriter:
    """One mp4 of AV1 video (LeRobot's defaults: SVT-AV1, yuv420p, crf 30, a key frame every
    2 frames); frame i is shown at i / fps seconds, so episodes appended one after another
    start where the previous ended."""

    def __init__(self, path: Path, fps: float, height: int, width: int):
        import av

        if height % 2 or width % 2:
            raise FrameError(f"{width}x{height} images cannot be {VIDEO_PIX_FMT} video; "
                             "expected even sides")
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path, self.frames, self.bytes = path, 0, 0
        self.container = av.open(str(path), "w")
        self.stream = self.container.add_stream(VIDEO_CODEC, rate=Fraction(fps).limit_denominator(),
                                                options=dict(VIDEO_OPTIONS))
        self.stream.height, self.stream.width, self.stream.pix_fmt = height, width, VIDEO_PIX_FMT
        self.time_base = Fraction(1) / Fraction(fps).limit_denominator()

    def write(self, images: np.ndarray) -> None:
        import av

        for image in images:
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format="rgb24")
            frame.pts, frame.time_base = self.frames, self.time_base
            self._mux(self.stream.encode(frame))
            self.frames += 1

    def _mux(self, packets) -> None:
        for packet in packets:
            self.bytes += packet.size
            self.container.mux(packet)

    def close(self) -> None:
        self._mux(self.stream.encode(None))
        self.container.close()
