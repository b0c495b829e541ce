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


class SegmentError(FrameError):
    """A segment's frames are wrong; `segment` is its position in the list asked for."""

    def __init__(self, segment: int, message: str):
        super().__init__(message)
        self.segment = segment


SEEK_GAP = 2.0  # s: a later segment further on than this is sought, nearer ones decoded through


def decode_video(path: Path, segments: list[tuple[float, int]], fps: float) -> list[np.ndarray]:
    """Each (start, count) segment's frames, at start, start + 1/fps, ... seconds, as uint8
    [count, H, W, 3]: an episode's part of a v3.0 file (many episodes), or a whole v2.x episode
    file. Every frame must sit on its slot within TIME_TOLERANCE, none missing, none extra.
    Segments are read in time order in one pass with one decoder (setting a decoder up per
    episode cost about 15% of the decoding, measured), seeking only across a gap."""
    import av

    out: list[np.ndarray | None] = [None] * len(segments)
    current = -1
    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                raise FrameError("holds no video stream")
            stream = container.streams.video[0]
            stream.thread_type = "AUTO"
            decoded, pending, last = None, None, float("-inf")
            for current in sorted(range(len(segments)), key=lambda i: segments[i][0]):
                start, count = segments[current]
                if decoded is None or start - last > SEEK_GAP or start < last - TIME_TOLERANCE:
                    # to the key frame at or before the segment (LeRobot's g=2: near)
                    container.seek(max(0, int(start / stream.time_base)), stream=stream)
                    decoded, pending = container.decode(stream), None
                frames, found = None, 0
                while True:
                    frame = pending if pending is not None else next(decoded, None)
                    pending = None
                    if frame is None:
                        break
                    if frame.time is None:
                        raise FrameError(f"a frame after {last:.4f} s has no timestamp")
                    last = frame.time
                    offset = frame.time - start
                    if offset < -TIME_TOLERANCE:
                        continue
                    slot = round(offset * fps)
                    if slot >= count:
                        pending = frame  # the next segment's first frame, maybe
                        break
                    if abs(offset - slot / fps) > TIME_TOLERANCE or slot != found:
                        raise FrameError(f"frame at {frame.time:.4f} s is not frame {found} of "
                                         f"the segment from {start:.4f} s at {fps:g} fps")
                    if frames is None:
                        frames = np.empty((count, frame.height, frame.width, 3), np.uint8)
                    frames[found] = frame.to_ndarray(format="rgb24")
                    found += 1
                if found != count:
                    raise FrameError(f"holds {found} frames from {start:.4f} s; expected "
                                     f"{count} at {fps:g} fps")
                out[current] = frames
    except FrameError as err:
        raise SegmentError(max(current, 0), str(err)) from None
    except av.error.FFmpegError as err:
        raise SegmentError(max(current, 0), f"not a readable video ({_why(err)})") from None
    return out


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
