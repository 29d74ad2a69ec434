"""Image files: linear RGB EXR in and out, sRGB PNG previews."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import OpenEXR

from .errors import ClrefractError

PathLike = str | os.PathLike


@contextlib.contextmanager
def atomic_path(path: PathLike, suffix: str = "") -> Iterator[Path]:
    """Yield a temp path beside `path`; on success it replaces `path` in one step.

    Readers never see a half-written file, and a failed write leaves the old file intact.
    `suffix` keeps the extension for writers that pick the format from it.
    """
    path = Path(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + suffix, dir=path.parent)
    except OSError as e:
        raise ClrefractError(f"{path}: cannot write here ({e.strerror or e})") from None
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        os.replace(tmp, path)
    except OSError as e:
        raise ClrefractError(f"{path}: cannot write ({e.strerror or e})") from None
    finally:
        tmp.unlink(missing_ok=True)


def ensure_out_dir(path: PathLike, what: str = "output folder") -> Path:
    """An output folder that exists and can be written, made if missing; refused in one line
    when it is a file or read-only, before any work is done."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ClrefractError(f"{path}: {what} exists and is not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ClrefractError(f"{path}: cannot make the {what} ({e.strerror or e})") from None
    try:  # a real write: access() says yes to root on any folder, even a read-only mount
        fd, probe = tempfile.mkstemp(prefix=".clrefract-probe.", dir=path)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise ClrefractError(f"{path}: {what} is not writable ({e.strerror or e})") from None
    return path


def _rgb_channel_names(names: list[str]) -> tuple[str, str, str] | None:
    """R,G,B if present, else X.R,X.G,X.B for a single layer X (e.g. 'rgba.R')."""
    if {"R", "G", "B"} <= set(names):
        return ("R", "G", "B")
    layers = sorted({n.rsplit(".", 1)[0] for n in names if "." in n})
    found = [ly for ly in layers if {f"{ly}.R", f"{ly}.G", f"{ly}.B"} <= set(names)]
    if len(found) == 1:
        ly = found[0]
        return (f"{ly}.R", f"{ly}.G", f"{ly}.B")
    return None


def read_exr_rgb(path: PathLike) -> np.ndarray:
    """Linear RGB (H, W, 3) float32 from an EXR with float or half R, G, B channels."""
    return read_exr_rgba(path)[0]


def read_exr_rgba(path: PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """Linear RGB (H, W, 3) float32 of an EXR, and its alpha (H, W) (None without an A
    channel), as stored: not un-premultiplied."""
    path = Path(path)
    if not path.is_file():
        raise ClrefractError(f"{path}: EXR file not found")
    try:
        # Separate channels: we pick R,G,B by name rather than trust the packed 'RGB(A)' view.
        with OpenEXR.File(str(path), separate_channels=True) as f:
            channels = {name: ch.pixels for name, ch in f.channels().items()}
    except Exception as e:  # OpenEXR raises RuntimeError with a C-level message
        raise ClrefractError(f"{path}: not a readable EXR file ({e})") from None
    names = _rgb_channel_names(list(channels))
    if names is None:
        raise ClrefractError(
            f"{path}: EXR has no R, G, B channels (found: {', '.join(sorted(channels)) or 'none'})"
        )
    planes = [np.asarray(channels[n]) for n in names]
    if any(p.ndim != 2 or p.shape != planes[0].shape for p in planes):
        raise ClrefractError(f"{path}: R, G, B channels differ in size (subsampled channels?)")
    rgb = np.ascontiguousarray(np.stack(planes, axis=-1), dtype=np.float32)
    a_name = names[0][:-1] + "A"  # 'A' beside 'R', or 'layer.A' beside 'layer.R'
    alpha = np.asarray(channels[a_name], np.float32) if a_name in channels else None
    if alpha is not None and alpha.shape != planes[0].shape:
        raise ClrefractError(f"{path}: alpha channel differs in size from R, G, B")
    return rgb, alpha


HDR_SUFFIXES = (".hdr", ".pic", ".rgbe")


def read_hdr_rgb(path: PathLike) -> np.ndarray:
    """Linear RGB (H, W, 3) float32 of a Radiance RGBE (.hdr) file: flat or run-length
    encoded scanlines, as Radiance and OpenCV write them. Values are decoded as OpenCV does
    (mantissa * 2^(exponent - 136)); an EXPOSURE line is not undone, as by most readers."""
    path = Path(path)
    if not path.is_file():
        raise ClrefractError(f"{path}: .hdr file not found")
    try:
        data = path.read_bytes()
    except OSError as e:
        raise ClrefractError(f"{path}: cannot read ({e.strerror or e})") from None

    def bad(why: str) -> ClrefractError:
        return ClrefractError(f"{path}: not a valid Radiance .hdr file ({why})")

    if not data.startswith(b"#?"):
        raise bad("no '#?' signature")
    end = data.find(b"\n\n")
    if end < 0:
        raise bad("header does not end")
    fmt = [ln for ln in data[:end].split(b"\n") if ln.startswith(b"FORMAT=")]
    if fmt and fmt[-1].strip() != b"FORMAT=32-bit_rle_rgbe":
        raise bad(f"{fmt[-1].decode('latin-1')}: only 32-bit_rle_rgbe is read")
    eol = data.find(b"\n", end + 2)
    size = data[end + 2 : eol if eol >= 0 else len(data)].split()
    if len(size) != 4 or size[0] not in (b"-Y", b"+Y") or size[2] != b"+X":
        raise bad(f"resolution line {b' '.join(size).decode('latin-1')!r} is not '-Y H +X W'")
    try:
        h, w = int(size[1]), int(size[3])
    except ValueError:
        raise bad("resolution is not two numbers") from None
    if h < 1 or w < 1:
        raise bad(f"size {w}x{h}")
    buf = np.frombuffer(data, np.uint8, offset=eol + 1) if eol >= 0 else np.zeros(0, np.uint8)
    rgbe = np.empty((h, w, 4), np.uint8)
    pos, n = 0, len(buf)
    for y in range(h):
        if 8 <= w < 32768 and pos + 4 <= n and buf[pos] == 2 and buf[pos + 1] == 2:
            if (int(buf[pos + 2]) << 8 | int(buf[pos + 3])) != w or buf[pos + 2] & 0x80:
                raise bad(f"scanline {y} has the wrong length")
            pos += 4
            for c in range(4):
                x = 0
                while x < w:
                    if pos >= n:
                        raise bad("file is truncated")
                    count = int(buf[pos])
                    if count > 128:  # a run of one value
                        count -= 128
                        if x + count > w or pos + 1 >= n:
                            raise bad(f"scanline {y} overruns")
                        rgbe[y, x : x + count, c] = buf[pos + 1]
                        pos += 2
                    else:  # literal bytes
                        if count == 0 or x + count > w or pos + 1 + count > n:
                            raise bad(f"scanline {y} overruns")
                        rgbe[y, x : x + count, c] = buf[pos + 1 : pos + 1 + count]
                        pos += 1 + count
                    x += count
        else:  # flat pixels (old-style run-length encoding is not read)
            if pos + 4 * w > n:
                raise bad("file is truncated")
            line = buf[pos : pos + 4 * w].reshape(w, 4)
            if np.any((line[:, 0] == 1) & (line[:, 1] == 1) & (line[:, 2] == 1)):
                raise bad("old-style run-length encoding is not read")
            rgbe[y] = line
            pos += 4 * w
    e = rgbe[..., 3].astype(np.int32)
    scale = np.where(e > 0, np.ldexp(1.0, e - 136), 0.0).astype(np.float32)
    rgb = rgbe[..., :3].astype(np.float32) * scale[..., None]
    return rgb[::-1].copy() if size[0] == b"+Y" else rgb


PHOTO_SUFFIXES = (".png", ".jpg", ".jpeg")
# an 8-bit value at or above this clipped in the camera: its radiance is unknown
SATURATED = 254 / 255


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """Inverse of the sRGB OETF for encoded values in [0, 1]; float32 out."""
    x = np.asarray(x, dtype=np.float32)
    hi = np.power((x + 0.055) / 1.055, 2.4, dtype=np.float32)
    return np.where(x <= 0.04045, x / 12.92, hi).astype(np.float32)


def read_pillow(path: PathLike, what: str, kind: str) -> np.ndarray:
    """The pixels of an 8- or 16-bit image file, or a one-line error naming it."""
    path = Path(path)
    if not path.is_file():
        raise ClrefractError(f"{path}: {what} file not found")
    try:
        return np.asarray(iio.imread(path, plugin="pillow"))
    except Exception:  # imageio's messages suggest plugins to install; not useful here
        raise ClrefractError(f"{path}: not a readable {kind}") from None


# JPEG's YCbCr (ITU-R BT.601, full range) of sRGB-encoded RGB: rows Y, Cb, Cr
YCC = np.array([[0.299, 0.587, 0.114], [-0.168736, -0.331264, 0.5], [0.5, -0.418688, -0.081312]])


def chroma_halved(path: PathLike) -> bool:
    """Whether a file is a JPEG whose chroma is stored at half the resolution both ways
    (4:2:0, Pillow's default and most cameras'); read from its header alone."""
    from PIL import Image, JpegImagePlugin

    try:
        with Image.open(path) as im:
            return im.format == "JPEG" and JpegImagePlugin.get_sampling(im) == 2
    except (OSError, ValueError):
        return False


def _unblur(x: np.ndarray, axis: int) -> np.ndarray:
    """Solve [1, 6, 1] / 8 (its ends 7/8 and 1/8: edges replicated) along an axis."""
    from scipy.linalg import solve_banded

    n = x.shape[axis]
    if n == 1:
        return x
    bands = np.empty((3, n))
    bands[0], bands[1], bands[2] = 1 / 8, 6 / 8, 1 / 8
    bands[1, [0, -1]] = 7 / 8
    moved = np.moveaxis(x, axis, 0)
    out = solve_banded((1, 1), bands, moved.reshape(n, -1)).reshape(moved.shape)
    return np.moveaxis(out, 0, axis)


def stored_chroma(encoded: np.ndarray) -> np.ndarray:
    """A 4:2:0 JPEG's decoded sRGB values (H, W, 3) in [0, 1], each pixel's chroma replaced
    by the sample its 2 x 2 block stored, the luma kept. libjpeg (Pillow's decoder) upsamples
    chroma by a triangle filter (3/4 and 1/4 of the nearest samples each way), so the
    mean over a block is the stored samples filtered by [1, 6, 1] / 8 each way, solved here
    for them: the decoder's smear of colour edges is undone, its quantisation kept."""
    x = np.asarray(encoded, np.float64)
    h, w = x.shape[:2]
    x = np.pad(x, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")
    ycc = x @ YCC.T
    means = ycc[:, :, 1:].reshape(x.shape[0] // 2, 2, x.shape[1] // 2, 2, 2).mean(axis=(1, 3))
    stored = _unblur(_unblur(means, 0), 1)
    ycc[:, :, 1:] = stored.repeat(2, axis=0).repeat(2, axis=1)
    rgb = ycc @ np.linalg.inv(YCC).T
    return np.clip(rgb[:h, :w], 0.0, 1.0).astype(np.float32)


def read_photo_rgb(path: PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Linear RGB (H, W, 3) float32 of an sRGB PNG or JPEG (8 or 16 bits, grey or colour,
    alpha ignored), and the (H, W) bool map of pixels clipped in some channel."""
    return read_photo(path)[:2]


def read_photo(
    path: PathLike, chroma: str = "decoded"
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """read_photo_rgb's linear RGB and clipped map, and the alpha (H, W) in [0, 1] of a
    grey+alpha or RGBA file (None without one). RGB is used as stored: not premultiplied.
    chroma="stored": a 4:2:0 JPEG's colour as its blocks stored it (stored_chroma)."""
    raw = read_pillow(path, "image", "PNG or JPEG image")
    if raw.dtype not in (np.uint8, np.uint16) or raw.ndim not in (2, 3):
        raise ClrefractError(f"{path}: unsupported image layout {raw.shape} of {raw.dtype}")
    if raw.ndim == 2:
        raw = raw[:, :, None]
    top = float(np.iinfo(raw.dtype).max)
    rgb = raw[:, :, :3] if raw.shape[2] >= 3 else np.repeat(raw[:, :, :1], 3, axis=2)
    encoded = rgb.astype(np.float32) / top
    saturated = (encoded >= SATURATED - 1e-6).any(axis=2)
    alpha = raw[:, :, -1].astype(np.float32) / top if raw.shape[2] in (2, 4) else None
    if chroma == "stored" and chroma_halved(path):
        encoded = stored_chroma(encoded)
    return srgb_to_linear(encoded), saturated, alpha


def read_frame(path: PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """A training or test frame: linear RGB, and the clipped-pixel map (None for EXR, whose
    values are radiance and never clip at a known level)."""
    return read_frame_rgba(path)[:2]


def read_frame_rgba(path: PathLike, chroma: str = "decoded"):
    """read_frame's linear RGB and clipped map, and the frame's alpha (None without one);
    chroma as read_photo's."""
    if Path(path).suffix.lower() in PHOTO_SUFFIXES:
        return read_photo(path, chroma)
    rgb, alpha = read_exr_rgba(path)
    return rgb, None, alpha


def write_exr_rgb(path: PathLike, img: np.ndarray, half: bool = False) -> None:
    """Write (H, W, 3) linear RGB as a ZIP-compressed EXR, float32 (or half), atomically."""
    img = np.asarray(img)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"write_exr_rgb: expected (H, W, 3), got {img.shape}")
    data = np.ascontiguousarray(img, dtype=np.float16 if half else np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path, suffix=".exr") as tmp:
        # A single 'RGB' array is written as the standard R, G, B channels.
        with OpenEXR.File(header, {"RGB": data}) as f:
            f.write(str(tmp))


def linear_to_srgb(img: np.ndarray) -> np.ndarray:
    """Standard sRGB OETF on values clipped to [0, 1] (NaN counts as 0); float32 out."""
    x = np.clip(np.nan_to_num(np.asarray(img, dtype=np.float32), nan=0.0), 0.0, 1.0)
    hi = 1.055 * np.power(x, 1.0 / 2.4, dtype=np.float32) - 0.055
    return np.where(x <= 0.0031308, 12.92 * x, hi).astype(np.float32)


def _to_uint8(img: np.ndarray) -> np.ndarray:
    img = np.asarray(img)
    if img.dtype == np.uint8:
        return img
    x = np.clip(np.nan_to_num(img.astype(np.float32), nan=0.0), 0.0, 1.0)
    return np.round(x * 255.0).astype(np.uint8)


def write_png(path: PathLike, img: np.ndarray) -> None:
    """8-bit PNG from uint8, or from floats taken as already-encoded values in [0, 1]."""
    img = np.asarray(img)
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (1, 3, 4)):
        raise ValueError(f"write_png: expected (H, W) or (H, W, 1|3|4), got {img.shape}")
    with atomic_path(path, suffix=".png") as tmp:
        iio.imwrite(tmp, _to_uint8(img), extension=".png")


def write_png_srgb(path: PathLike, img_linear: np.ndarray) -> None:
    """sRGB-encoded 8-bit PNG preview of a linear image."""
    write_png(path, linear_to_srgb(img_linear))


def image_size(path: PathLike) -> tuple[int, int]:
    """(width, height) of an EXR or ordinary image, reading as little as possible."""
    path = Path(path)
    try:
        if path.suffix.lower() == ".exr":
            with OpenEXR.File(str(path), header_only=True) as f:
                lo, hi = f.header()["dataWindow"]
            return int(hi[0] - lo[0] + 1), int(hi[1] - lo[1] + 1)
        # Pillow reads PNG/JPEG; naming it keeps imageio from trying every plugin on a bad file.
        shape = iio.improps(path, plugin="pillow").shape
        return int(shape[1]), int(shape[0])
    except Exception:  # imageio's messages suggest plugins to install; not useful here
        raise ClrefractError(f"{path}: cannot read the image size (not a readable image)") from None
