"""Making SVG safe and self-contained for inlining into one HTML page.

Figures come from matplotlib or from study code (stored artifacts); either may carry
comments with label text, metadata, scripts or references to outside resources. Inlining
several SVGs into one page also makes their element ids share one namespace, so each
figure's ids get a prefix of their own.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET

SVG_NS = "http://www.w3.org/2000/svg"
XLINK_NS = "http://www.w3.org/1999/xlink"
ET.register_namespace("", SVG_NS)
ET.register_namespace("xlink", XLINK_NS)

#: Elements dropped with their content: active content, embedded foreign documents and
#: metadata (which names outside vocabularies by URL).
DROPPED = {"script", "foreignObject", "metadata", "iframe", "object", "embed", "audio",
           "video"}
#: Embedded rasters (matplotlib's ``imshow``) are kept: they are data, not links.
RASTER = re.compile(r"data:image/(png|jpeg|gif);base64,")
_HREFS = ("href", f"{{{XLINK_NS}}}href")
_URL_REF = re.compile(r"url\(\s*['\"]?#([^)'\"\s]+)['\"]?\s*\)")


class SvgError(ValueError):
    """Text that is not a well-formed SVG document."""


def _local(tag: str) -> str:
    return tag.rpartition("}")[2] if isinstance(tag, str) else ""


def clean(svg_text: str, prefix: str, keep_style: bool = True) -> str:
    """A sanitised copy of ``svg_text`` with every id prefixed by ``prefix``.

    An inline ``<style>`` applies to the whole page, not to its figure alone: with
    ``keep_style=False`` (figures the report did not draw itself) style elements are dropped.

    Drops :data:`DROPPED` elements, comments and processing instructions, event-handler
    attributes (``on*``), links that do not point inside the figure (embedded PNG, JPEG or
    GIF images excepted), and CSS that reaches
    outside (``@import``, ``url(...)`` other than ``url(#id)``). Returns the ``<svg>``
    element alone (no XML declaration or doctype), ready to inline.
    """
    text = re.sub(r"<!DOCTYPE[^>]*>", "", svg_text, count=1)
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise SvgError(f"not well-formed SVG: {exc}") from None
    if _local(root.tag) != "svg":
        raise SvgError(f"root element is <{_local(root.tag)}>, not <svg>")
    _prune(root, DROPPED if keep_style else DROPPED | {"style"})
    ids = {el.get("id") for el in root.iter() if el.get("id")}

    def rename(match: re.Match) -> str:
        name = match.group(1)
        return f"url(#{prefix}{name})" if name in ids else "none"

    for el in root.iter():
        for key, value in list(el.attrib.items()):
            if key == "id":
                el.set(key, prefix + value)
            elif key in _HREFS and value.startswith("#"):
                el.set(key, f"#{prefix}{value[1:]}")
            elif "url(" in value:
                el.set(key, _URL_REF.sub(rename, value))
        if _local(el.tag) == "style" and el.text:
            el.text = _safe_css(_URL_REF.sub(rename, el.text))
    return ET.tostring(root, encoding="unicode")


def _prune(parent: ET.Element, dropped: set[str]) -> None:
    for child in list(parent):
        tag = child.tag
        if not isinstance(tag, str) or _local(tag) in dropped:
            parent.remove(child)
            continue
        for key in list(child.attrib):
            value = child.attrib[key]
            name = _local(key).lower()
            if name.startswith("on"):
                del child.attrib[key]
            elif key in _HREFS and not (value.startswith("#") or (
                    _local(tag) == "image" and RASTER.match(value))):
                del child.attrib[key]
            elif "url(" in value and re.search(r"url\(\s*['\"]?[^#'\"\s]", value):
                del child.attrib[key]
        _prune(child, dropped)
    for key in [k for k in parent.attrib if _local(k).lower().startswith("on")]:
        del parent.attrib[key]


def _safe_css(css: str) -> str:
    """CSS without imports or references outside the figure."""
    css = re.sub(r"@import[^;]*;?", "", css)
    return re.sub(r"url\(\s*['\"]?[^#)'\"\s][^)]*\)", "none", css)
