"""report.html in a real headless Chromium (Debian package ``chromium``) driven by Playwright.

The page must load offline with no console errors and no network request, show the right defect
count, and respond to hover (tooltip), click (selection highlights the table row and vice versa),
sorting and zoom. Set PAVEMAP_UPDATE_SCREENSHOT=1 to refresh docs/report_screenshot.png.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from browser_support import launched, open_page
from pavemap.export import write_outputs
from pavemap.export.report import write_report
from pavemap.export.sample import sample_inputs

sync_api = pytest.importorskip("playwright.sync_api", reason="playwright not installed (pip install playwright)")
DOCS = Path(__file__).resolve().parents[1] / "docs" / "report_screenshot.png"


@pytest.fixture(scope="module")
def browser():
    with launched() as b:
        yield b


def column(page, key: str) -> int:
    """1-based position of the defects-table column ``key`` (columns come and go with the records' keys)."""
    keys = page.eval_on_selector_all("#defects thead th", "els => els.map(e => e.dataset.key)")
    return keys.index(key) + 1


def view_width(page) -> float:
    return float(page.get_attribute("#map", "viewBox").split()[2])


def test_report_interactions(browser, tmp_path):
    kw = sample_inputs(9, seed=5)
    kw.pop("trajectory")
    n = len(kw["instances"])
    path = write_report(tmp_path, kw["instances"], bev_rgb=kw["bev_rgb"], bev_semantic=kw["bev_semantic"],
                        mesh_grid=kw["mesh_grid"], prob_map=kw["prob_map"], grid=kw["grid"], metrics=kw["metrics"],
                        config=kw["config"], detections=kw["detections"])
    page, problems = open_page(browser, path)
    assert page.inner_text("#defect-count") == str(n)
    assert page.locator("#defects tbody tr").count() == n
    assert page.locator("#map path.d").count() == n

    # default order: priority (repair now first)
    ranks = [int(v) for v in page.eval_on_selector_all(f"#defects tbody tr td:nth-child({column(page, 'priority')})",
                                                       "els => els.map(e => e.dataset.v)")]
    assert ranks == sorted(ranks)

    # hover a defect marker: the tooltip shows its properties
    target = kw["instances"][3]
    page.hover(f'#map circle.mk[data-id="{target.id}"]')
    assert page.is_visible("#tooltip")
    tip = page.inner_text("#tooltip")
    assert f"#{target.id} {target.code}" in tip and "severity" in tip

    # click it: the table row is selected
    page.click(f'#map circle.mk[data-id="{target.id}"]')
    assert "sel" in page.get_attribute(f'#defects tr[data-id="{target.id}"]', "class")
    assert f"#{target.id}" in page.inner_text("#selected")

    # click another table row: its polygon is highlighted and the map zooms to it
    other = kw["instances"][6]
    w0 = view_width(page)
    page.click(f'#defects tr[data-id="{other.id}"]')
    assert "sel" in page.get_attribute(f'#map path.d[data-id="{other.id}"]', "class")
    assert "sel" not in (page.get_attribute(f'#defects tr[data-id="{target.id}"]', "class") or "")
    assert view_width(page) < w0

    # sorting by area (descending on first click)
    page.click('#defects th[data-key="area_m2"]')
    areas = [float(v) for v in page.eval_on_selector_all(f"#defects tbody tr td:nth-child({column(page, 'area_m2')})",
                                                         "els => els.map(e => e.dataset.v)")]
    assert areas == sorted(areas, reverse=True)

    # zoom buttons and the mouse wheel change the view; "fit" restores it
    page.click("#zoom-home")
    w_home = view_width(page)
    page.click("#zoom-in")
    assert view_width(page) < w_home
    page.click("#zoom-home")
    box = page.locator("#map").bounding_box()
    page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    page.mouse.wheel(0, -400)
    page.wait_for_function(f"parseFloat(document.getElementById('map').getAttribute('viewBox').split(' ')[2]) "
                           f"< {w_home}")
    # class filter hides rows and shapes
    code = kw["instances"][0].code
    page.uncheck(f'input[data-code="{code}"]')
    hidden = sum(i.code == code for i in kw["instances"])
    assert page.inner_text("#shown-count") == str(n - hidden)
    assert not problems, problems
    page.close()


def test_report_without_defects(browser, tmp_path):
    path = write_report(tmp_path, [], detections=[{"frame": 0, "camera": "C", "box": [0, 0, 4, 4], "cls": 1,
                                                   "conf": 0.2, "kept": False, "reason": "off road"}])
    page, problems = open_page(browser, path)
    assert page.inner_text("#defect-count") == "0"
    assert "No defects were mapped" in page.inner_text("#no-defects")
    assert page.locator("#defects tbody tr").count() == 0
    assert not problems, problems
    page.close()


def shoot(page, pick_id: int, path: Path) -> None:
    """Screenshot with one defect selected from the table, the map zoomed around it and its tooltip shown."""
    page.click(f'#defects tr[data-id="{pick_id}"]')  # selects and zooms the map onto it
    page.evaluate("window.scrollTo(0, 0)")
    for _ in range(4):  # back out to show the neighbourhood
        page.click("#zoom-out")
    page.hover(f'#map circle.mk[data-id="{pick_id}"]')
    page.screenshot(path=str(path))


def test_realistic_report_screenshot(browser, tmp_path):
    """A full run-like report (figures included) loads cleanly and can be screenshot.

    PAVEMAP_UPDATE_SCREENSHOT=1 copies the shot to docs/report_screenshot.png; with
    PAVEMAP_SCREENSHOT_REPORT=/path/to/report.html (e.g. a `pavemap demo` run) that report is shot instead.
    """
    given = os.environ.get("PAVEMAP_SCREENSHOT_REPORT")
    if given:
        report = Path(given)
    else:
        kw = sample_inputs(18, seed=11, geo=True, layout="crossing")
        traj = kw.pop("trajectory")
        report = write_outputs(tmp_path, figures_extra={"sweep": [{"tau_conf": t, "msr": 0.9 - t, "orp": 0.6 + t / 2}
                                                                  for t in (0.05, 0.1, 0.2, 0.3, 0.5)]},
                               trajectory=traj, progress=False, **kw)["report.html"]
    page, problems = open_page(browser, report, viewport=(1600, 1240))
    n = int(page.inner_text("#defect-count"))
    if not given:
        assert n == 18 and page.locator("#figures img").count() == 2
    shot = tmp_path / "shot.png"
    if n:
        # the most severe defect, as an engineer would look at first
        pick = page.eval_on_selector_all("#defects tbody tr", "els => els.map(e => e.dataset.id)")[0]
        shoot(page, int(pick), shot)
    else:
        page.screenshot(path=str(shot))
    assert shot.stat().st_size > 50_000
    assert not problems, problems
    if os.environ.get("PAVEMAP_UPDATE_SCREENSHOT") == "1":
        DOCS.parent.mkdir(exist_ok=True)
        shutil.copyfile(shot, DOCS)
    page.close()
