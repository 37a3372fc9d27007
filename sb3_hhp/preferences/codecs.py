"""How the preference store writes what it keeps: images as PNG, observations as ``.npy`` / ``.npz`` bytes (never
pickled), a query's ``info`` as JSON."""

import enum
import io
import json
import pathlib
from typing import Any, Union

import cv2
import numpy as np

__all__ = ["decode_array", "decode_png", "encode_array", "encode_info", "encode_png"]


def encode_png(image: np.ndarray, name: str = "image") -> bytes:
    """Encode an RGB(A) or grayscale uint8 image as PNG bytes (lossless).

    :param image: array (H, W), (H, W, 1), (H, W, 3) RGB or (H, W, 4) RGBA of dtype uint8
    :param name: what the image is, for the error message
    :return: the PNG file's bytes
    """
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise ValueError(f"{name} must be a uint8 image, got dtype {image.dtype}; convert it with .astype(np.uint8)")
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    elif image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_RGBA2BGRA)
    elif image.ndim != 2:
        raise ValueError(f"{name} must have shape (H, W), (H, W, 1), (H, W, 3) or (H, W, 4), got {image.shape}")
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise ValueError(f"{name} is empty (shape {image.shape})")
    ok, buffer = cv2.imencode(".png", np.ascontiguousarray(image))
    if not ok:  # pragma: no cover - cv2 fails only on unsupported layouts, rejected above
        raise ValueError(f"OpenCV could not encode {name} of shape {image.shape} as PNG")
    return buffer.tobytes()


def decode_png(data: bytes) -> np.ndarray:
    """Decode PNG bytes written by :func:`encode_png` back to an RGB(A) or grayscale uint8 array."""
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError("The stored bytes are not a PNG image")
    if image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    elif image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGBA)
    return image


def encode_array(value: Any, name: str) -> bytes:
    """An observation as ``.npy`` bytes, or ``.npz`` bytes for a dict observation (no pickling)."""
    buffer = io.BytesIO()
    if isinstance(value, dict):
        np.savez(buffer, **{str(key): np.asarray(item) for key, item in value.items()})
    else:
        array = np.asarray(value)
        if array.dtype == object:
            raise ValueError(f"{name} must be a numeric array (or a dict of arrays), got an object array")
        np.save(buffer, array, allow_pickle=False)
    return buffer.getvalue()


def decode_array(data: bytes) -> Union[np.ndarray, dict]:
    """An observation written by :func:`encode_array`."""
    if data[:2] == b"PK":  # a zip archive: np.savez of a dict observation
        with np.load(io.BytesIO(data), allow_pickle=False) as archive:
            return {key: archive[key] for key in archive.files}
    return np.load(io.BytesIO(data), allow_pickle=False)


def _json_default(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, enum.Enum):
        return value.value
    if isinstance(value, (set, frozenset)):
        return sorted(value, key=repr)
    if isinstance(value, (pathlib.PurePath, bytes)):
        return str(value)
    raise TypeError(f"Query.info holds a {type(value).__name__}, which cannot be stored as JSON")


def encode_info(info: dict) -> str:
    """A query's ``info`` as JSON (numpy arrays and numbers, enums, sets and paths turned into JSON's own)."""
    if not isinstance(info, dict):
        raise ValueError(f"Query.info must be a dict, got {type(info).__name__}")
    try:
        return json.dumps(info, default=_json_default, allow_nan=True)
    except TypeError as error:
        raise ValueError(f"{error}; keep Query.info to numbers, strings, lists, dicts and numpy arrays") from error
