"""A minimal reader of the PDFs Chromium prints (Skia's writer), numpy and the standard library only (no PDF
package is a dependency): each page's MediaBox, where its images and filled rectangles land (the content
streams' q/Q/cm transforms followed, form XObjects included), the scale at which text is drawn (0.75 pt per
CSS px at 100 %: less means the page was shrunk to fit something too wide), and its text decoded through each
font's ToUnicode map (what a PDF reader's copy and search see). Used by tests/test_report.py's print check."""
from __future__ import annotations

import re
import zlib
from dataclasses import dataclass, field

import numpy as np

OBJ = re.compile(rb"(\d+) 0 obj\s*(.*?)endobj", re.S)
TOKEN = re.compile(rb"<[0-9A-Fa-f\s]*>|\((?:\\.|[^\\)])*\)|\[|\]|/[^\s/\[\]<>()]+|[-+]?\d*\.?\d+|[A-Za-z'\"*]+")


@dataclass
class PdfPage:
    box: tuple[float, float, float, float]  # MediaBox
    scales: list[float] = field(default_factory=list)  # |det|^0.5 of the CTM at each drawn image
    images: list[tuple[float, float, float, float]] = field(default_factory=list)  # x0, y0, x1, y1 (pt)
    rects: list[tuple[float, float, float, float]] = field(default_factory=list)  # filled rectangles (pt)
    text: str = ""
    text_scales: list[float] = field(default_factory=list)  # CTM scale at each text run: 0.75 = CSS px at 100 %


def _stream(body: bytes) -> bytes:
    m = re.search(rb"stream\r?\n(.*?)\r?\nendstream", body, re.S)
    return zlib.decompress(m.group(1)) if b"/FlateDecode" in body[:m.start()] else m.group(1)


def _ref(body: bytes, key: bytes) -> int | None:
    m = re.search(rb"/" + key + rb"\s+(\d+) 0 R", body)
    return int(m.group(1)) if m else None


def _names(body: bytes, key: bytes, objs: dict[int, bytes]) -> dict[bytes, int]:
    """name -> object of a resource sub-dictionary (/Font, /XObject), inline or indirect."""
    m = re.search(rb"/" + key + rb"\s*<<(.*?)>>", body, re.S)
    if not m:
        ref = _ref(body, key)
        if ref is None:
            return {}
        inner = objs[ref]
    else:
        inner = m.group(1)
    return {n: int(r) for n, r in re.findall(rb"/([^\s/]+)\s+(\d+) 0 R", inner)}


def _cmap(data: bytes) -> dict[int, str]:
    out: dict[int, str] = {}
    for block in re.findall(rb"beginbfchar(.*?)endbfchar", data, re.S):
        for a, b in re.findall(rb"<([0-9A-Fa-f]+)>\s*<([0-9A-Fa-f]+)>", block):
            out[int(a, 16)] = bytes.fromhex(b.decode()).decode("utf-16-be", "replace")
    for block in re.findall(rb"beginbfrange(.*?)endbfrange", data, re.S):
        for a, b, c in re.findall(rb"<([0-9A-Fa-f]+)>\s*<([0-9A-Fa-f]+)>\s*<([0-9A-Fa-f]+)>", block):
            start = int(c, 16)
            for k, code in enumerate(range(int(a, 16), int(b, 16) + 1)):
                out[code] = chr(start + k)
    return out


def read_pdf(data: bytes) -> list[PdfPage]:
    objs = {int(m.group(1)): m.group(2) for m in OBJ.finditer(data)}
    cmaps: dict[int, dict[int, str]] = {}
    pages = []
    for num in sorted(k for k, b in objs.items() if re.search(rb"/Type\s*/Page\b", b)):
        body = objs[num]
        box = tuple(float(v) for v in re.search(rb"/MediaBox\s*\[([^\]]*)\]", body).group(1).split())
        page = PdfPage(box)
        res = objs[_ref(body, b"Resources")] if _ref(body, b"Resources") else body
        contents = [int(r) for r in re.findall(rb"(\d+) 0 R", re.search(rb"/Contents\s*(\[[^\]]*\]|\d+ 0 R)",
                                                                         body).group(1))]
        text: list[str] = []
        for c in contents:
            _run(_stream(objs[c]), res, objs, np.eye(3), page, text, cmaps)
        page.text = "".join(text)
        pages.append(page)
    return pages


def _font(ref: int, objs: dict[int, bytes], cmaps: dict[int, dict[int, str]]) -> dict[int, str]:
    """The font object ``ref``'s ToUnicode map (code -> text), read once into ``cmaps``."""
    if ref not in cmaps:
        tu = _ref(objs[ref], b"ToUnicode")
        cmaps[ref] = _cmap(_stream(objs[tu])) if tu else {}
    return cmaps[ref]


def _decoded(operands: list[bytes], font: dict[int, str]) -> list[str]:
    """The text of a text-showing operator's hex strings (2-byte codes) through the font's map."""
    out = []
    for s in operands:
        if s.startswith(b"<"):
            h = re.sub(rb"\s", b"", s[1:-1]).decode()
            out.append("".join(font.get(int(h[i:i + 4], 16), "?") for i in range(0, len(h), 4)))
    return out


def _draw(x: bytes, objs: dict[int, bytes], ctm: np.ndarray, page: PdfPage, text: list[str],
          cmaps: dict[int, dict[int, str]]) -> None:
    """An XObject drawn at ``ctm``: an image's box and scale, or a form's content run through its matrix."""
    if b"/Image" in x:
        corners = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], float)
        page.images.append(_bbox(corners, ctm))
        page.scales.append(float(np.sqrt(abs(np.linalg.det(ctm[:2, :2])))))
    elif b"/Form" in x:
        m = re.search(rb"/Matrix\s*\[([^\]]*)\]", x)
        sub = ctm
        if m:
            a, b, c, d, e, f = (float(v) for v in m.group(1).split())
            sub = np.array([[a, b, 0], [c, d, 0], [e, f, 1]]) @ ctm
        inner = objs[_ref(x, b"Resources")] if _ref(x, b"Resources") else x
        _run(_stream(x), inner, objs, sub, page, text, cmaps)


def _run(content: bytes, res: bytes, objs: dict[int, bytes], ctm: np.ndarray, page: PdfPage, text: list[str],
         cmaps: dict[int, dict[int, str]]) -> None:
    fonts, xobjects = _names(res, b"Font", objs), _names(res, b"XObject", objs)
    stack, operands, font, path = [], [], {}, []
    for tok in TOKEN.findall(content):
        if tok[:1].isalpha() or tok in (b"'", b'"'):
            op = tok
            if op == b"q":
                stack.append(ctm.copy())
            elif op == b"Q":
                ctm = stack.pop()
            elif op == b"cm":
                a, b, c, d, e, f = (float(v) for v in operands[-6:])
                ctm = np.array([[a, b, 0], [c, d, 0], [e, f, 1]]) @ ctm
            elif op == b"re":
                x, y, w, h = (float(v) for v in operands[-4:])
                path.append((x, y, w, h))
            elif op in (b"f", b"F", b"f*"):
                for x, y, w, h in path:
                    page.rects.append(_bbox(np.array([[x, y], [x + w, y], [x, y + h], [x + w, y + h]]), ctm))
                path = []
            elif op in (b"n", b"S", b"B", b"b", b"W", b"W*"):
                if op != b"W" and op != b"W*":
                    path = []
            elif op == b"Tf":
                ref = fonts.get(operands[-2][1:])
                if ref is not None:
                    font = _font(ref, objs, cmaps)
            elif op in (b"Tj", b"TJ", b"'", b'"'):
                page.text_scales.append(float(np.sqrt(abs(np.linalg.det(ctm[:2, :2])))))
                text.extend(_decoded(operands, font))
            elif op in (b"ET", b"Td", b"TD", b"T*", b"Tm") and text and not text[-1].endswith(" "):
                text.append(" ")
            elif op == b"Do":
                ref = xobjects.get(operands[-1][1:])
                if ref is not None:
                    _draw(objs[ref], objs, ctm, page, text, cmaps)
            operands = []
        elif tok not in (b"[", b"]"):
            operands.append(tok)


def _bbox(corners: np.ndarray, ctm: np.ndarray) -> tuple[float, float, float, float]:
    p = np.c_[corners, np.ones(len(corners))] @ ctm
    return float(p[:, 0].min()), float(p[:, 1].min()), float(p[:, 0].max()), float(p[:, 1].max())
