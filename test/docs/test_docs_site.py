"""The Sphinx site: it builds with warnings and unresolved references as errors (what
``make docs`` runs), its generated parameter tables equal the settings classes, and it renders
in a real headless browser (Chromium): the landing page with its table of contents, a
parameter table and an API page, and the navigation beside the text in a 1280 px window and on
a 1000 px laptop screen.

The site is built once per test module into a temporary directory, offline (no extension
fetches anything). Chromium comes from ``make setup-tests``, which ``make test`` runs
(``apt-get install chromium``); without it the browser tests fail and say so.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from collections.abc import Iterator
from html.parser import HTMLParser
from pathlib import Path

import pytest

from haptic_topology.config.node_params import KNOWN

REPO = Path(__file__).resolve().parents[2]
DOCS = REPO / 'docs'
sys.path.insert(0, str(DOCS / '_ext'))

from haptic_params import row_cells  # noqa: E402  (docs/_ext is not a package)


@pytest.fixture(scope='module')
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The HTML site, built as ``make docs`` builds it (-W --keep-going -n)."""
    out = tmp_path_factory.mktemp('site') / 'html'
    build = subprocess.run(
        [sys.executable, '-m', 'sphinx', '-b', 'html', '-W', '--keep-going', '-n', '-q',
         str(DOCS), str(out)],
        capture_output=True, text=True, timeout=600, cwd=REPO)
    assert build.returncode == 0, (
        f'sphinx-build failed (exit {build.returncode}):\n{build.stdout}\n{build.stderr}')
    return out


class _Tables(HTMLParser):
    """Text of every cell of every ``<table>`` with a given class, as rows of strings."""

    def __init__(self, css_class: str) -> None:
        super().__init__()
        self.css_class = css_class
        self.tables: list[list[list[str]]] = []
        self._depth = 0        # inside a matching table
        self._cell: list[str] | None = None

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        classes = (dict(attrs).get('class') or '').split()
        if tag == 'table' and self.css_class in classes:
            self._depth = 1
            self.tables.append([])
        elif self._depth and tag == 'tr':
            self.tables[-1].append([])
        elif self._depth and tag in ('td', 'th'):
            self._cell = []

    def handle_endtag(self, tag: str) -> None:
        if self._depth and tag in ('td', 'th') and self._cell is not None:
            self.tables[-1][-1].append(' '.join(''.join(self._cell).split()))
            self._cell = None
        elif self._depth and tag == 'table':
            self._depth = 0

    def handle_data(self, data: str) -> None:
        if self._cell is not None:
            self._cell.append(data)


def tables(html: str, css_class: str) -> list[list[list[str]]]:
    parser = _Tables(css_class)
    parser.feed(html)
    return parser.tables


def nodes_with_parameters() -> list[str]:
    return [node for node, specs in KNOWN.items() if specs is not None]


# -- the build ---------------------------------------------------------------------------------
def test_the_site_builds_with_warnings_as_errors(site: Path) -> None:
    for page in ('index.html', 'parameters.html', 'concepts.html', 'cli.html',
                 'api/device.html', 'results.html'):
        assert (site / page).is_file(), page


def test_parameter_tables_equal_the_settings_classes(site: Path) -> None:
    """Each generated table holds, row by row, the declared parameters of its node: name,
    ROS type, default, range or choices, live flag and description."""
    rendered = tables((site / 'parameters.html').read_text(encoding='utf-8'), 'haptic-params')
    nodes = nodes_with_parameters()
    assert len(rendered) == len(nodes)
    for node, table in zip(nodes, rendered, strict=True):
        specs = KNOWN[node]
        assert specs is not None
        want = [[' '.join(c.split()) for c in row_cells(spec)] for spec in specs.values()]
        assert table[1:] == want, node
        assert table[0][0] == 'parameter'


def test_the_table_parser_reads_cells() -> None:
    html = ('<table class="x haptic-params"><tr><th>parameter</th></tr>'
            '<tr><td><code>a</code> b</td><td>1</td></tr></table><table><tr><td>no</td></tr>'
            '</table>')
    assert tables(html, 'haptic-params') == [[['parameter'], ['a b', '1']]]


def test_the_equation_table_links_every_cited_equation_to_the_api(site: Path) -> None:
    html = (site / 'concepts.html').read_text(encoding='utf-8')
    rows = tables(html, 'haptic-equations')
    assert rows, 'no equation table on the concepts page'
    numbers = [row[0] for row in rows[0][1:]]
    for eq in ('eq. 2', 'eq. 10', 'eq. 13', 'eq. 14', 'eq. 17', 'eq. 20'):
        assert eq in numbers
    assert 'href="api/control.html#haptic_topology.control.laws.penalty_control"' in html


# -- in a browser ------------------------------------------------------------------------------
def chromium() -> str:
    for name in ('chromium', 'chromium-browser', 'google-chrome'):
        path = shutil.which(name)
        if path:
            return path
    pytest.fail('chromium not found: the rendered-site tests need a headless browser; '
                '`make setup-tests` (part of `make test`) installs it (apt-get install chromium)')


@pytest.fixture(scope='module')
def browser(tmp_path_factory: pytest.TempPathFactory) -> Iterator[list[str]]:
    profile = tmp_path_factory.mktemp('chromium-profile')
    yield [chromium(), '--headless', '--no-sandbox', '--disable-gpu', '--no-first-run',
           '--disable-dev-shm-usage', f'--user-data-dir={profile}']


def rendered_dom(browser: list[str], page: Path, width: int = 1280) -> str:
    """The DOM of ``page`` after Chromium has loaded and laid it out (scripts run) in a
    window ``width`` px wide."""
    run = subprocess.run([*browser, f'--window-size={width},900', '--dump-dom', page.as_uri()],
                         capture_output=True, text=True, timeout=180)
    assert run.returncode == 0, f'chromium exited {run.returncode}: {run.stderr[-2000:]}'
    assert '<body' in run.stdout, f'no DOM from chromium: {run.stderr[-2000:]}'
    return run.stdout


def test_the_landing_page_renders_with_theme_and_table_of_contents(
        site: Path, browser: list[str]) -> None:
    dom = rendered_dom(browser, site / 'index.html')
    assert '<title>haptic_topology' in dom
    assert 'class="wy-nav-side"' in dom, 'the theme did not render its navigation'
    assert '_static/css/theme.css' in dom and (site / '_static' / 'css' / 'theme.css').is_file()
    for entry in ('Getting started', 'Concepts: the paper in code', 'Node parameters',
                  'Devices', 'API reference', 'Changelog'):
        assert f'>{entry}</a>' in dom, f'table of contents lacks {entry!r}'


def test_a_parameter_page_renders_its_generated_rows(site: Path, browser: list[str]) -> None:
    dom = rendered_dom(browser, site / 'parameters.html')
    rendered = tables(dom, 'haptic-params')
    first = nodes_with_parameters()[0]
    specs = KNOWN[first]
    assert specs is not None
    names = [row[0] for row in rendered[0][1:]]
    assert names == list(specs)
    assert 'watchdog_timeout' in names


def test_an_api_page_renders_the_backend_interface(site: Path, browser: list[str]) -> None:
    dom = rendered_dom(browser, site / 'api' / 'device.html')
    for target in ('haptic_topology.device.backend.DeviceBackend',
                   'haptic_topology.device.backend.DeviceBackend.configure',
                   'haptic_topology.device.backend.DeviceBackend.read',
                   'haptic_topology.device.backend.DeviceReading',
                   'haptic_topology.device.maglev.MaglevModel'):
        assert f'id="{target}"' in dom, f'autodoc rendered no entry for {target}'
    assert 'A haptic device as seen by' in dom, 'the docstring of DeviceBackend is missing'


#: Run at the end of a copy of a page: the boxes, in CSS px, of the page's text (``role="main"``)
#: and of its navigation: the largest element holding the link to the Getting started page that
#: does not also hold the text (the sidebar, whatever the theme calls it). Written into the DOM
#: for ``--dump-dom`` to carry out.
_LAYOUT_PROBE = """<script>
(function () {
  const box = (e) => { const r = e.getBoundingClientRect();
    return {left: r.left, right: r.right, top: r.top, bottom: r.bottom}; };
  const main = document.querySelector('[role="main"]');
  const links = Array.from(document.querySelectorAll('a[href="getting_started.html"]'))
    .filter((a) => !main.contains(a));
  let nav = links.length ? links[0] : null;
  while (nav && nav.parentElement && !nav.parentElement.contains(main)) nav = nav.parentElement;
  const out = {width: window.innerWidth, main: box(main), nav: nav ? box(nav) : null};
  document.body.setAttribute('data-layout', JSON.stringify(out));
})();
</script>"""


def layout(browser: list[str], site: Path, page: str, width: int) -> dict[str, object]:
    """Where the text and the navigation of ``page`` lie in a ``width`` px window."""
    html = (site / page).read_text(encoding='utf-8')
    assert '</body>' in html, page
    probe = site / f'_layout_probe_{width}.html'   # beside the page: its relative links hold
    probe.write_text(html.replace('</body>', _LAYOUT_PROBE + '</body>', 1), encoding='utf-8')
    dom = rendered_dom(browser, probe, width)
    start = dom.find('data-layout="')
    assert start >= 0, 'the layout probe did not run'
    raw = dom[start + len('data-layout="'):dom.index('"', start + len('data-layout="'))]
    result: dict[str, object] = json.loads(raw.replace('&quot;', '"').replace('&amp;', '&'))
    return result


@pytest.mark.parametrize('width', [1280, 1000])
def test_the_navigation_stays_beside_the_text(site: Path, browser: list[str],
                                              width: int) -> None:
    """In a 1280 px window and on a 1000 px laptop screen, a page's navigation is a column left
    of its text, both starting in the first screen, not a block stacked above or below it."""
    got = layout(browser, site, 'concepts.html', width)
    assert got['width'] == width, f'chromium laid the page out {got["width"]} px wide'
    nav, main = got['nav'], got['main']
    assert isinstance(nav, dict) and isinstance(main, dict), f'no navigation found: {got}'
    assert nav['right'] <= main['left'], (
        f'at {width} px the navigation {nav} is not left of the text {main}')
    assert nav['top'] < main['bottom'] and main['top'] < nav['bottom'], (
        f'at {width} px the navigation {nav} and the text {main} do not lie side by side')
    assert main['top'] < 900 and nav['top'] < 900, (
        f'at {width} px the text {main} or the navigation {nav} starts below the first screen')
    assert main['right'] - main['left'] >= 480, f'at {width} px the text is narrow: {main}'
