"""The report's HTML: one self-contained page (inline CSS, JS and data-URI images; no network, no server)."""

from __future__ import annotations

import html
import json
from dataclasses import dataclass, field

CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:0;background:#f4f5f7;color:#1d1f23}
header{background:#1d2733;color:#fff;padding:14px 24px}header h1{margin:0;font-size:20px}
header p{margin:4px 0 0;color:#b8c4d0;font-size:13px}
nav{padding:6px 24px;background:#27333f;font-size:13px}nav a{color:#cfe3ff;margin-right:14px;text-decoration:none}
main{padding:12px 24px;max-width:1500px}
section{background:#fff;border-radius:8px;padding:12px 18px;margin:14px 0;box-shadow:0 1px 3px rgba(0,0,0,.08)}
section h2{font-size:17px;margin:4px 0 10px}
section.missing{background:#fafafa;color:#666}section.missing h2:after{content:" (missing)";color:#a66;font-weight:400}
.note{color:#555;font-size:13px;margin:6px 0}
.row{display:flex;flex-wrap:wrap;gap:12px;align-items:flex-start}
figure{margin:0;flex:1 1 300px;min-width:220px;max-width:720px}figure img,figure svg{width:100%;height:auto;display:block;
border:1px solid #ddd;background:#111}figcaption{font-size:12px;color:#444;margin-top:3px}
figure.plot img,figure.plot svg{background:#fff}figure.small{max-width:380px}
table{border-collapse:collapse;font-size:13px;margin:6px 0}td,th{border-bottom:1px solid #e3e5e8;padding:3px 9px;
text-align:left;vertical-align:top}th{background:#f0f2f5}td.num{text-align:right;font-variant-numeric:tabular-nums}
.ok{color:#137333;font-weight:600}.bad{color:#c5221f;font-weight:600}.na{color:#888}
.scale{display:flex;align-items:center;gap:6px;font-size:12px;margin-top:4px}.scale .bar{flex:1;height:12px;
border:1px solid #bbb}
.slider{display:flex;align-items:center;gap:10px;margin:8px 0}.slider input{flex:1}
.legend{font-size:12px;color:#333}.legend span{margin-right:12px;white-space:nowrap}
.sw{display:inline-block;width:10px;height:10px;margin-right:4px;vertical-align:middle;border:1px solid #666}
"""

# One generic slider: <input data-slider="KEY"> switches every <img data-slot="KEY:COLUMN"> to frame i of
# DATA[KEY][COLUMN] and every <span data-text="KEY:COLUMN"> to DATA[KEY].text[COLUMN][i].
JS = """
(function(){
  var DATA = JSON.parse(document.getElementById('report-data').textContent);
  function show(key, i){
    var d = DATA[key]; if(!d) return;
    document.querySelectorAll('img[data-slot^="'+key+':"]').forEach(function(img){
      var col = img.getAttribute('data-slot').split(':')[1];
      if(d.images[col] && d.images[col][i]) img.src = d.images[col][i];
    });
    document.querySelectorAll('[data-text^="'+key+':"]').forEach(function(el){
      var col = el.getAttribute('data-text').split(':')[1];
      if(d.text[col]) el.textContent = d.text[col][i];
    });
    document.querySelectorAll('[data-marker="'+key+'"]').forEach(function(el){
      var xs = JSON.parse(el.getAttribute('data-xs')); el.setAttribute('x', xs[i]);
    });
  }
  document.querySelectorAll('input[data-slider]').forEach(function(s){
    s.addEventListener('input', function(){ show(s.getAttribute('data-slider'), parseInt(s.value, 10)); });
    show(s.getAttribute('data-slider'), parseInt(s.value, 10));
  });
})();
"""


@dataclass
class Section:
    """One titled block of the page; missing=True renders it greyed out with the reason as its body."""

    id: str
    title: str
    body: str
    missing: bool = False


@dataclass
class Page:
    title: str
    subtitle: str
    sections: list[Section] = field(default_factory=list)
    data: dict = field(default_factory=dict)
    """Slider data: {key: {"images": {column: [uri, ...]}, "text": {column: [str, ...]}}}."""

    def add(self, section: Section) -> None:
        self.sections.append(section)

    def render(self) -> str:
        nav = "".join(f'<a href="#{s.id}">{html.escape(s.title)}</a>' for s in self.sections)
        body = "\n".join(
            f'<section id="{s.id}" class="{"missing" if s.missing else "present"}"><h2>{html.escape(s.title)}</h2>\n'
            f"{s.body}</section>" for s in self.sections
        )
        data = json.dumps(self.data, separators=(",", ":")).replace("</", "<\\/")
        return (
            "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\"><title>{html.escape(self.title)}</title>"
            f"<link rel=\"icon\" href=\"data:,\"><style>{CSS}</style></head><body>\n"
            f"<header><h1>{html.escape(self.title)}</h1><p>{html.escape(self.subtitle)}</p></header>\n<nav>{nav}</nav>\n"
            f"<main>\n{body}\n</main>\n<script type=\"application/json\" id=\"report-data\">{data}</script>\n"
            f"<script>{JS}</script>\n</body></html>\n"
        )


def missing(id: str, title: str, reason: str) -> Section:
    return Section(id, title, f'<p class="note">{html.escape(reason)}</p>', missing=True)


def figure(src: str, caption: str, *, slot: str | None = None, plot: bool = False, extra: str = "",
           small: bool = False) -> str:
    """<figure> with an <img>; slot="KEY:COLUMN" lets a slider swap its frames; small: at most 380 px wide."""
    attr = f' data-slot="{slot}"' if slot else ""
    names = " ".join(n for n, on in (("plot", plot), ("small", small)) if on)
    cls = f' class="{names}"' if names else ""
    return (f'<figure{cls}><img src="{src}" alt="{html.escape(caption)}"{attr}>'
            f"<figcaption>{html.escape(caption)}</figcaption>{extra}</figure>")


def svg_figure(svg: str, caption: str, extra: str = "") -> str:
    return f'<figure class="plot">{svg}<figcaption>{html.escape(caption)}</figcaption>{extra}</figure>'


def slider(key: str, n: int, label_col: str, start: int = 0, what: str = "frame") -> str:
    return (f'<div class="slider"><label for="slider-{key}">{html.escape(what)}</label>'
            f'<input type="range" id="slider-{key}" data-slider="{key}" min="0" max="{max(n - 1, 0)}" value="{start}" step="1">'
            f'<span data-text="{key}:{label_col}"></span></div>')


def table(header: list[str], rows: list[list], num_cols: set[int] = frozenset(), raw_cols: set[int] = frozenset()) -> str:
    """An HTML table; cells in raw_cols are inserted as HTML, the rest escaped."""
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    out = []
    for r in rows:
        cells = []
        for i, c in enumerate(r):
            text = c if i in raw_cols else html.escape("" if c is None else str(c))
            cells.append(f'<td class="num">{text}</td>' if i in num_cols else f"<td>{text}</td>")
        out.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(out)}</tbody></table>"


def fmt(v) -> str:
    """A metric value for humans: 3-4 significant digits, n/a for missing."""
    if v is None:
        return "n/a"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        a = abs(v)
        return f"{v:.1f}" if a >= 1000 else f"{v:.3f}" if a >= 1 else f"{v:.4g}"
    if isinstance(v, dict) and "reason" in v:
        return f"n/a ({v['reason']})"
    return str(v)
