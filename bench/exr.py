"""A small OpenEXR reader for the files Tessera writes, standard library only.

Tessera writes one-part scan-line EXR files with 32-bit float channels and ZIP
compression (crates/tessera-image: `Encoding::SMALL_LOSSLESS`). This reads exactly that
family: single part, scan lines, NONE / RLE / ZIPS / ZIP compression, UINT, HALF and FLOAT
channels (OpenEXR file layout, "Technical Introduction" and "OpenEXR File Layout"). Tiled,
deep and multi-part files, and the lossy compressions, are refused with a message.

    img = read_exr("out.exr")      # {"width", "height", "channels": {name: [float]}, "attrs"}
    r = img["channels"]["R"]       # row-major, width * height values
"""
import struct
import zlib

_COMPRESSION = {0: "NONE", 1: "RLE", 2: "ZIPS", 3: "ZIP"}
_LINES_PER_BLOCK = {0: 1, 1: 1, 2: 1, 3: 16}
_SIZE = {0: 4, 1: 2, 2: 4}  # UINT, HALF, FLOAT


def _cstr(b, i):
    j = b.index(b"\0", i)
    return b[i:j].decode("latin-1"), j + 1


def _channels(value):
    out, i = [], 0
    while value[i] != 0:
        name, i = _cstr(value, i)
        ptype, _plinear, _xs, _ys = struct.unpack_from("<iB3xii", value, i)
        i += 16
        out.append((name, ptype))
    return out


def _undo_zip(raw):
    """Inverse of the ZIP/RLE pre-pass: a delta predictor, then two interleaved halves."""
    t = bytearray(raw)
    for i in range(1, len(t)):
        t[i] = (t[i - 1] + t[i] - 128) & 0xFF
    half = (len(t) + 1) // 2
    out = bytearray(len(t))
    out[0::2] = t[:half]
    out[1::2] = t[half:]
    return bytes(out)


def _unrle(data, size):
    out, i = bytearray(), 0
    while i < len(data):
        n = struct.unpack_from("<b", data, i)[0]
        i += 1
        if n < 0:
            out += data[i:i - n]
            i -= n
        else:
            out += data[i:i + 1] * (n + 1)
            i += 1
    if len(out) != size:
        raise ValueError("EXR: RLE block decodes to %d bytes, expected %d" % (len(out), size))
    return bytes(out)


def read_exr(path):
    with open(path, "rb") as f:
        b = f.read()
    magic, version = struct.unpack_from("<ii", b, 0)
    if magic != 20000630:
        raise ValueError("%s: not an OpenEXR file" % path)
    if version & 0x1E00:  # tiled (0x200), long names are fine, deep (0x800), multi-part (0x1000)
        if version & 0x200 or version & 0x800 or version & 0x1000:
            raise ValueError("%s: tiled, deep or multi-part EXR not supported" % path)
    i, attrs = 8, {}
    while b[i] != 0:
        name, i = _cstr(b, i)
        typ, i = _cstr(b, i)
        size = struct.unpack_from("<i", b, i)[0]
        i += 4
        attrs[name] = (typ, b[i:i + size])
        i += size
    i += 1
    chans = _channels(attrs["channels"][1])
    comp = attrs["compression"][1][0]
    if comp not in _COMPRESSION:
        raise ValueError("%s: compression %d not supported" % (path, comp))
    x0, y0, x1, y1 = struct.unpack("<iiii", attrs["dataWindow"][1])
    w, h = x1 - x0 + 1, y1 - y0 + 1
    lines = _LINES_PER_BLOCK[comp]
    nblocks = (h + lines - 1) // lines
    offsets = struct.unpack_from("<%dQ" % nblocks, b, i)
    data = {name: [0.0] * (w * h) for name, _ in chans}
    fmt = {0: "I", 1: "e", 2: "f"}
    for off in offsets:
        y, size = struct.unpack_from("<ii", b, off)
        chunk = b[off + 8:off + 8 + size]
        rows = min(lines, y1 + 1 - y)
        raw_size = rows * w * sum(_SIZE[t] for _, t in chans)
        if size < raw_size:
            if comp in (2, 3):
                chunk = _undo_zip(zlib.decompress(chunk))
            elif comp == 1:
                chunk = _undo_zip(_unrle(chunk, raw_size))
        if len(chunk) != raw_size:
            raise ValueError("%s: block at y=%d has %d bytes, expected %d" % (path, y, len(chunk), raw_size))
        j = 0
        for r in range(rows):
            row = (y - y0 + r) * w
            for name, t in chans:
                n = _SIZE[t] * w
                data[name][row:row + w] = struct.unpack_from("<%d%s" % (w, fmt[t]), chunk, j)
                j += n
    text = {k: v[1].decode("utf-8", "replace") for k, v in attrs.items() if v[0] == "string"}
    return {"width": w, "height": h, "channels": data, "attrs": text}
