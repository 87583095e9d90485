"""``report.html`` in a real browser: headless Chromium (Debian ``chromium`` + ``chromium-driver``) via Selenium.

Opens the page of a comparison of two real ``evaluate.py`` runs (three bent icospheres) and checks: no console
error, one table row per run (sorted by a click on a header), linked cameras, and non-blank pixels in a 3-D
view's canvas (a screenshot of the element: the WebGL view drew the mesh, not only the page around it).
Skipped, with the reason, where Chromium, its driver or Selenium is missing.
"""

from __future__ import annotations

import io
import shutil
import tempfile
import time

import numpy as np
import pytest

from shapecorr.cli.compare import write_comparison
from shapecorr.cli.evaluate import evaluate

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")
pytest.importorskip("selenium", reason="selenium is not installed (pip install selenium)")
NO_BROWSER = "no chromium / chromedriver on PATH (apt-get install chromium chromium-driver)"
pytestmark = [pytest.mark.browser, pytest.mark.usefixtures("single_thread"),
              pytest.mark.skipif(CHROMIUM is None or CHROMEDRIVER is None, reason=NO_BROWSER)]
#: Chromium's headless flags on machines without a display, GPU or network: software WebGL (SwiftShader),
#: no background connections (refused on sandboxed machines), a fresh profile.
HEADLESS_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader", "--disable-quic",
                  "--no-first-run", "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--window-size=1400,1000")
#: Seconds to wait for the 3-D views to be drawn.
DRAW_TIMEOUT = 60.0


def _driver():
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in (*HEADLESS_FLAGS, f"--user-data-dir={tempfile.mkdtemp(prefix='chromium-profile-')}"):
        options.add_argument(flag)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    return webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)


@pytest.fixture(scope="module")
def report(tmp_path_factory, evaluate_on_folder, bent_sphere_folder):
    """The ``report.html`` of two runs (descriptor NN, ground truth) with two example pairs."""
    root = bent_sphere_folder(tmp_path_factory.mktemp("browser_folder"), ["p0", "p1", "p2"])
    cache, base = tmp_path_factory.mktemp("browser_cache"), tmp_path_factory.mktemp("browser_runs")
    for name, model in (("nn", "descriptor_nn"), ("gt", "identity_gt")):
        evaluate(evaluate_on_folder(root, cache, base / name, f"model={model}"))
    write_comparison([base / "nn", base / "gt"], base / "cmp", names=["nn", "gt"], n_examples=2)
    return base / "cmp" / "report.html"


def test_report_in_headless_chromium(report):
    from PIL import Image
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select, WebDriverWait

    driver = _driver()
    try:
        driver.get(report.as_uri())
        WebDriverWait(driver, DRAW_TIMEOUT).until(
            lambda d: len(d.find_elements(By.CSS_SELECTOR, "#view-0 canvas")) > 0)
        time.sleep(1.0)  # the first frame of the WebGL scene
        rows = driver.find_elements(By.CSS_SELECTOR, "#runs tbody tr")
        assert [r.find_elements(By.TAG_NAME, "td")[0].text for r in rows] == ["nn", "gt"]
        view = driver.find_element(By.ID, "view-0")
        driver.execute_script("arguments[0].scrollIntoView()", view)
        pixels = np.asarray(Image.open(io.BytesIO(view.screenshot_as_png)).convert("RGB"), dtype=np.int16)
        # the mesh, not the white background: many pixels far from white and several distinct colours
        coloured = (np.abs(pixels - 255).sum(axis=2) > 60)
        assert coloured.mean() > 0.05, f"only {coloured.mean():.3%} of the 3-D view is drawn"
        assert len(np.unique(pixels[coloured].reshape(-1, 3) // 32, axis=0)) > 8
        # the views of one pair are linked: moving the target's camera moves the runs' cameras
        eye = driver.execute_async_script("""
            const done = arguments[arguments.length - 1];
            const a = document.getElementById('view-target'), b = document.getElementById('view-1');
            Plotly.relayout(a, {'scene.camera': {eye: {x: 1.5, y: 0.3, z: 0.4}}})
              .then(() => setTimeout(() => done(b.layout.scene.camera.eye), 500));""")
        assert eye == {"x": 1.5, "y": 0.3, "z": 0.4}
        # another example pair from the list: the same views redrawn for it
        first = driver.find_element(By.ID, "caption-0").text
        Select(driver.find_element(By.ID, "pair-select")).select_by_index(1)
        WebDriverWait(driver, DRAW_TIMEOUT).until(lambda d: d.find_element(By.ID, "caption-0").text != first)
        assert len(driver.find_elements(By.CSS_SELECTOR, "#view-0 canvas")) > 0
        header = driver.find_element(By.XPATH, "//table[@id='runs']//th[starts-with(., 'mean error')]")
        orders = []
        for _ in range(2):  # a click sorts ascending, the next one descending
            header.click()
            orders.append([r.find_elements(By.TAG_NAME, "td")[0].text
                           for r in driver.find_elements(By.CSS_SELECTOR, "#runs tbody tr")])
        assert orders == [["gt", "nn"], ["nn", "gt"]]
        errors = [e["message"] for e in driver.get_log("browser") if e["level"] == "SEVERE"]
        assert errors == []
    finally:
        driver.quit()


def test_broken_page_is_caught(tmp_path):
    """The console check can fail: a page with a script error reports it as SEVERE."""
    page = tmp_path / "broken.html"
    page.write_text("<html><body><script>undefinedFunction();</script></body></html>")
    driver = _driver()
    try:
        driver.get(page.as_uri())
        errors = [e["message"] for e in driver.get_log("browser") if e["level"] == "SEVERE"]
        assert any("undefinedFunction" in e for e in errors)
    finally:
        driver.quit()
