"""The msgpack-numpy dialects of openpi and vla-eval: round trips, hostile input, and the unmodified peers."""

import io

import msgpack
import numpy as np
import pytest
from PIL import Image

from openral_remote.codec import WireFormatError
from openral_remote.msgpack_numpy import Limits, array_header, decode_tree, packb, unpack_tree, unpackb


def _observation() -> dict[str, object]:
    return {
        "observation/image": np.arange(224 * 224 * 3, dtype=np.uint8).reshape(224, 224, 3),
        "observation/wrist_image": np.full((224, 224, 3), 7, dtype=np.uint8),
        "observation/state": np.linspace(-1, 1, 8, dtype=np.float32),
        "mask": np.array([True, False]),
        "counts": np.arange(6, dtype=">i8").reshape(2, 3),
        "empty": np.zeros((0, 5), dtype=np.float64),
        "scale": np.float32(0.5),
        "prompt": "pick up the cube",
        "nested": {"k": [1, 2.5, None, b"raw"]},
    }


def _assert_same(decoded: dict[str, object], sent: dict[str, object]) -> None:
    assert decoded.keys() == sent.keys()
    for key, value in sent.items():
        if isinstance(value, np.ndarray):
            got = decoded[key]
            assert isinstance(got, np.ndarray), key
            assert (got.dtype, got.shape) == (value.dtype, value.shape), key
            np.testing.assert_array_equal(got, value)
        else:
            assert decoded[key] == value, key


def test_openpi_round_trip_is_byte_stable_and_read_only() -> None:
    sent = _observation()
    data = packb(sent)
    decoded = unpackb(data)
    _assert_same(decoded, sent)
    assert type(decoded["scale"]) is np.float32
    assert not decoded["observation/image"].flags.writeable
    assert packb(decoded) == data


def test_openpi_keys_are_bytes_and_dialects_do_not_mix() -> None:
    raw = msgpack.unpackb(packb({"a": np.zeros(2, np.float32)}), raw=False)
    assert set(raw["a"]) == {b"__ndarray__", b"data", b"dtype", b"shape"}
    vla = packb({"a": np.zeros(2, np.float32)}, dialect="vla_eval")
    assert isinstance(unpackb(vla, dialect="openpi")["a"], dict)  # each side leaves the other's arrays alone
    assert isinstance(unpackb(packb({"a": np.zeros(2)}), dialect="vla_eval")["a"], dict)


def test_vla_eval_round_trip_sends_images_as_png_and_scalars_as_python() -> None:
    sent = {
        "images": {"agentview": np.random.default_rng(0).integers(0, 255, (16, 20, 3), dtype=np.uint8)},
        "states": np.arange(8, dtype=np.float64),
        "step": np.int64(3),
        "done": np.bool_(True),
    }
    data = packb(sent, dialect="vla_eval")
    raw = msgpack.unpackb(data, raw=False)
    assert raw["images"]["agentview"]["format"] == "png"
    assert raw["step"] == 3
    assert raw["done"] is True
    decoded = unpackb(data, dialect="vla_eval")
    np.testing.assert_array_equal(decoded["images"]["agentview"], sent["images"]["agentview"])  # type: ignore[index]
    np.testing.assert_array_equal(decoded["states"], sent["states"])
    raw_images = unpackb(packb(sent, dialect="vla_eval", image_format="raw"), dialect="vla_eval")
    np.testing.assert_array_equal(raw_images["images"]["agentview"], sent["images"]["agentview"])  # type: ignore[index]


def test_header_is_read_before_anything_is_decoded() -> None:
    tree = unpack_tree(packb({"img": np.zeros((4, 5, 3), np.uint8)}, dialect="vla_eval"), limits=Limits())
    header = array_header(tree["img"], dialect="vla_eval")
    assert header is not None
    assert header.shape == (4, 5, 3)
    assert header.image_format == "png"
    assert decode_tree(tree, dialect="vla_eval")["img"].shape == (4, 5, 3)


@pytest.mark.parametrize(
    "value",
    [np.array([object()], dtype=object), np.zeros(2, np.complex64), np.array(["a"]), np.zeros(2, np.longdouble)],
)
def test_encoding_refuses_what_decoding_would(value: np.ndarray) -> None:
    with pytest.raises(WireFormatError, match="cannot be sent"):
        packb({"x": value})


def test_encoding_refuses_unknown_objects() -> None:
    with pytest.raises(WireFormatError, match="cannot encode"):
        packb({"x": object()})


def _array(dtype: object = "<f4", shape: object = (2,), data: object = bytes(8)) -> bytes:
    return msgpack.packb({"x": {b"__ndarray__": True, b"data": data, b"dtype": dtype, b"shape": shape}})


@pytest.mark.parametrize(
    ("message", "reason"),
    [
        (_array(dtype="|O"), "dtype"),
        (_array(dtype="<U1"), "dtype"),
        (_array(dtype="|V8"), "dtype"),
        (_array(dtype="<c8"), "dtype"),
        (_array(dtype="<f16", data=bytes(32)), "dtype"),
        (_array(dtype="(2,)<f4"), "dtype"),
        (_array(dtype=4), "dtype"),
        (_array(shape=(3,)), "8 bytes announced as shape"),
        (_array(shape=(1,), data=bytes(8)), "8 bytes announced"),
        (_array(shape=(-2,)), "bad shape"),
        (_array(shape=(True, 2)), "bad shape"),
        (_array(shape=(2.0,)), "bad shape"),
        (_array(shape="2"), "bad shape"),
        (_array(shape=(1,) * 9, data=bytes(4)), "bad shape"),
        (_array(shape=(0, 1 << 40, 1 << 40)), "elements"),
        (_array(data="text"), "not bytes"),
        (msgpack.packb({"x": {b"__npgeneric__": True, b"data": 300, b"dtype": "|u1"}}), "numpy scalar"),
        (msgpack.packb({"x": {b"__npgeneric__": True, b"data": 1.5, b"dtype": "<i4"}}), "numpy scalar"),
        (msgpack.packb({"x": {b"__npgeneric__": True, b"data": "a", b"dtype": "<f4"}}), "numpy scalar"),
        (b"\xc1", "not a msgpack"),
        (msgpack.packb({"x": "y"})[:-1], "not a msgpack"),
        (msgpack.packb({"x": 1}) + b"\x00", "not a msgpack"),
        (msgpack.packb(msgpack.ExtType(5, b"abc")), "not a msgpack"),
        (msgpack.packb({1: 2}), "not a msgpack"),
    ],
)
def test_hostile_messages_are_refused(message: bytes, reason: str) -> None:
    with pytest.raises(WireFormatError, match=reason):
        unpackb(message)


def test_bounds_on_size_depth_and_entries() -> None:
    limits = Limits(max_bytes=1000, max_depth=4, max_entries=50, max_elements=100)
    with pytest.raises(WireFormatError, match="exceeds the limit"):
        unpackb(msgpack.packb(b"x" * 2000), limits=limits)
    deep: object = 1
    for _ in range(5):
        deep = [deep]
    with pytest.raises(WireFormatError, match="deeper"):
        unpackb(msgpack.packb(deep), limits=limits)
    with pytest.raises(WireFormatError, match="entries"):
        unpackb(msgpack.packb([[0] * 30, [0] * 30]), limits=limits)
    with pytest.raises(WireFormatError, match="not a msgpack"):  # one container too large: refused while parsing
        unpackb(msgpack.packb([0] * 60), limits=limits)
    with pytest.raises(WireFormatError, match="elements"):
        unpackb(packb(np.zeros(101, np.uint8)), limits=limits)
    with pytest.raises(WireFormatError, match="not a msgpack"):  # msgpack's own stack bound
        unpackb(b"\x91" * 5000 + b"\x00")


def _png(shape: tuple[int, ...], announced: list[int], fmt: str = "png", mode: str = "RGB") -> bytes:
    out = io.BytesIO()
    Image.new(mode, (shape[1], shape[0])).save(out, format="PNG")
    return msgpack.packb({"img": {"__image__": True, "format": fmt, "data": out.getvalue(), "shape": announced}})


@pytest.mark.parametrize(
    ("message", "reason"),
    [
        (_png((4, 5), [5, 4, 3]), "announced as"),
        (_png((4, 5), [4, 5, 4]), "announced as"),
        (_png((4, 5), [4, 5, 3], fmt="jpeg"), "undecodable jpeg"),
        (_png((4, 5), [4, 5, 3], fmt="gif"), "image format"),
        (_png((4, 5), [4, 5]), r"\(H, W, 1\|3\|4\)"),
        (_png((4, 5), [100_000, 100_000, 3]), "elements"),
        (
            msgpack.packb({"img": {"__image__": True, "format": "png", "data": b"\x89PNG junk", "shape": [4, 5, 3]}}),
            "undecodable png",
        ),
    ],
)
def test_hostile_images_are_refused_before_their_pixels_are_decoded(message: bytes, reason: str) -> None:
    with pytest.raises(WireFormatError, match=reason):
        unpackb(message, dialect="vla_eval")


def test_grey_and_rgba_images_decode_to_the_announced_shape() -> None:
    assert unpackb(_png((4, 5), [4, 5, 1], mode="L"), dialect="vla_eval")["img"].shape == (4, 5, 1)
    assert unpackb(_png((4, 5), [4, 5, 4], mode="RGBA"), dialect="vla_eval")["img"].shape == (4, 5, 4)


_OPENPI_PACK = """
import sys, numpy as np
from openpi_client import msgpack_numpy
obs = {
    "observation/image": np.arange(224 * 224 * 3, dtype=np.uint8).reshape(224, 224, 3),
    "observation/wrist_image": np.full((224, 224, 3), 7, dtype=np.uint8),
    "observation/state": np.linspace(-1, 1, 8, dtype=np.float32),
    "mask": np.array([True, False]),
    "counts": np.arange(6, dtype=">i8").reshape(2, 3),
    "empty": np.zeros((0, 5), dtype=np.float64),
    "scale": np.float32(0.5),
    "prompt": "pick up the cube",
    "nested": {"k": [1, 2.5, None, b"raw"]},
}
sys.stdout.buffer.write(msgpack_numpy.Packer().pack(obs))
"""

_OPENPI_UNPACK = """
import sys, numpy as np
from openpi_client import msgpack_numpy
obs = msgpack_numpy.unpackb(sys.stdin.buffer.read())
print(sorted(obs), obs["observation/state"].dtype, obs["counts"].dtype.str, type(obs["scale"]).__name__)
np.testing.assert_array_equal(obs["observation/image"], np.arange(224 * 224 * 3, dtype=np.uint8).reshape(224, 224, 3))
np.testing.assert_array_equal(obs["observation/state"], np.linspace(-1, 1, 8, dtype=np.float32))
np.testing.assert_array_equal(obs["counts"], np.arange(6).reshape(2, 3))
assert obs["nested"] == {"k": [1, 2.5, None, b"raw"]} and obs["empty"].shape == (0, 5)
print("ok")
"""


@pytest.mark.slow
def test_bytes_of_the_unmodified_openpi_client_decode_and_reencode_identically(peer_venv) -> None:  # type: ignore[no-untyped-def]
    peer = peer_venv("openpi-client")
    golden = peer.run(_OPENPI_PACK, text=False).stdout
    assert isinstance(golden, bytes)
    assert len(golden) > 2 * 224 * 224 * 3
    decoded = unpackb(golden)
    _assert_same(decoded, _observation())
    assert packb(decoded) == golden
    assert packb(_observation()) == golden
    out = peer.run(_OPENPI_UNPACK, input=packb(_observation()), text=False).stdout.decode()
    assert out.splitlines()[-1] == "ok", out
    assert "float32 >i8 float32" in out


_VLA_PACK = """
import sys, numpy as np
from vla_eval.protocol.messages import Message, MessageType, pack_message
obs = {"images": {"agentview": np.arange(16 * 20 * 3, dtype=np.uint8).reshape(16, 20, 3)},
       "states": np.linspace(0, 1, 8), "task_description": "put the bowl on the plate", "step": np.int64(4)}
sys.stdout.buffer.write(pack_message(Message(MessageType.OBSERVATION, obs, seq=3, timestamp=1.0)))
"""

_VLA_UNPACK = """
import sys, numpy as np
from vla_eval.protocol.messages import unpack_message
msg = unpack_message(sys.stdin.buffer.read())
np.testing.assert_array_equal(msg.payload["actions"], np.arange(14, dtype=np.float32).reshape(2, 7))
np.testing.assert_array_equal(msg.payload["image"], np.full((8, 6, 3), 9, np.uint8))
print(msg.type.value, msg.seq, msg.payload["actions"].dtype, msg.payload["n"])
"""


@pytest.mark.slow
def test_the_unmodified_vla_eval_codec_and_openral_read_each_other(peer_venv) -> None:  # type: ignore[no-untyped-def]
    peer = peer_venv("vla-eval")
    message = unpackb(peer.run(_VLA_PACK, text=False).stdout, dialect="vla_eval")
    assert message["type"] == "observation"
    assert message["seq"] == 3
    payload = message["payload"]
    np.testing.assert_array_equal(
        payload["images"]["agentview"], np.arange(16 * 20 * 3, dtype=np.uint8).reshape(16, 20, 3)
    )
    np.testing.assert_array_equal(payload["states"], np.linspace(0, 1, 8))
    assert payload["step"] == 4
    assert payload["task_description"] == "put the bowl on the plate"
    reply = {
        "type": "action",
        "seq": 3,
        "timestamp": 2.0,
        "payload": {
            "actions": np.arange(14, dtype=np.float32).reshape(2, 7),
            "image": np.full((8, 6, 3), 9, np.uint8),
            "n": np.int32(2),
        },
    }
    out = peer.run(_VLA_UNPACK, input=packb(reply, dialect="vla_eval"), text=False).stdout.decode()
    assert out.split() == ["action", "3", "float32", "2"]
