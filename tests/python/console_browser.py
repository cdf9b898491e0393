"""The operator's console in headless chromium (Python playwright, the system browser).

Usage: console_browser.py OPEN_URL TOKEN_URL TOKEN HIL_PLAN SCREENSHOT_DIR CHROMIUM

OPEN_URL: a daemon on loopback without a token, with `plans/demo.toml` in its plan library
and a schedule `nightly`; TOKEN_URL: a daemon with the token TOKEN. Prints one line per check
and `console: all checks passed` at the end; any failed check raises.
"""

import http.server
import json
import re
import sys
import threading
import time
import urllib.error
import urllib.request

from playwright.sync_api import sync_playwright

OPEN, GUARDED, TOKEN, HIL_PLAN, SHOTS, CHROMIUM = sys.argv[1:7]
ENDED = {"succeeded", "failed", "cancelled", "interrupted"}
JOB_TIMEOUT_S = 300


def api(base, path, method="GET", token=None, headers=None):
    """(status, decoded JSON or None) of one API request made outside the browser."""
    request = urllib.request.Request(base + path, method=method, headers=headers or {})
    if token:
        request.add_header("Authorization", f"Bearer {token}")
    try:
        with urllib.request.urlopen(request, timeout=60) as response:
            body = response.read()
            return response.status, (json.loads(body) if body else None)
    except urllib.error.HTTPError as e:
        body = e.read()
        return e.code, (json.loads(body) if body else None)


def job(base, job_id, token=None):
    status, body = api(base, f"/v1/jobs/{job_id}", token=token)
    assert status == 200, (status, body)
    return body


def wait_ended(base, job_id):
    deadline = time.time() + JOB_TIMEOUT_S
    while time.time() < deadline:
        j = job(base, job_id)
        if j["state"] in ENDED:
            return j
        time.sleep(0.2)
    raise AssertionError(f"job {job_id} did not end within {JOB_TIMEOUT_S} s")


def check(message):
    print(f"ok: {message}", flush=True)


def shot(page, name):
    page.screenshot(path=f"{SHOTS}/{name}.png", full_page=True)


def job_id_of(page):
    page.wait_for_url(re.compile(r".*#/jobs/\d+$"), timeout=60_000)
    return int(page.url.rsplit("/", 1)[1])


def submit_demo(page, plan="demo.toml"):
    page.goto(OPEN + "/#/jobs")
    page.wait_for_selector(f"#plan-select option[value='{plan}']", state="attached")
    page.select_option("#plan-select", plan)
    # A redraw (a job queued or ended elsewhere) must keep the operator's choice.
    page.evaluate("rerender()")
    chosen = page.locator("#plan-select").input_value()
    assert chosen == plan, f"a redraw of the jobs page reset the chosen plan to {chosen}"
    page.click("#submit-library")
    return job_id_of(page)


def no_sideways_scroll(page, what):
    page.wait_for_timeout(300)
    widths = page.evaluate(
        "[document.documentElement.scrollWidth, document.documentElement.clientWidth]"
    )
    assert widths[0] <= widths[1], f"{what}: the page scrolls sideways ({widths})"


# A page of another origin that POSTs a form to a daemon, as a hostile site would.
class Hostile(http.server.BaseHTTPRequestHandler):
    def do_GET(self):
        target = self.path.split("?to=", 1)[1]
        page = (
            "<!doctype html><form id=f method=post action='%s'>"
            "<input name=x value=1></form><script>f.submit()</script>" % target
        )
        self.send_response(200)
        self.send_header("Content-Type", "text/html")
        self.end_headers()
        self.wfile.write(page.encode())

    def log_message(self, *args):
        pass


def main():
    hostile = http.server.HTTPServer(("127.0.0.1", 0), Hostile)
    threading.Thread(target=hostile.serve_forever, daemon=True).start()
    hostile_url = f"http://127.0.0.1:{hostile.server_address[1]}"

    with sync_playwright() as p:
        browser = p.chromium.launch(
            executable_path=CHROMIUM, headless=True, args=["--no-sandbox"]
        )
        context = browser.new_context(viewport={"width": 1280, "height": 900})
        page = context.new_page()
        errors = []
        page.on("pageerror", lambda e: errors.append(str(e)))

        # The demo from the plan library: its progress moves on the job's page to succeeded.
        first = submit_demo(page)
        # Two more runs of the same machine, queued behind it from a second tab.
        second_tab = context.new_page()
        others = [submit_demo(second_tab, "demo-2.toml"), submit_demo(second_tab, "demo-3.toml")]
        second_tab.close()
        seen, state = set(), ""
        deadline = time.time() + JOB_TIMEOUT_S
        while time.time() < deadline:
            shown = page.locator("[data-progress]").first
            if shown.count():
                seen.add(shown.get_attribute("data-progress"))
            badge = page.locator("h1 .state")
            state = badge.inner_text() if badge.count() else ""
            if state in ENDED:
                break
            time.sleep(0.1)
        assert state == "succeeded", f"job {first} shown {state!r}"
        page.wait_for_selector("[data-progress]")
        final = page.locator("[data-progress]").first.get_attribute("data-progress")
        done, total = map(int, final.split("/"))
        between = [v for v in seen if 0 < int(v.split("/")[0]) < int(v.split("/")[1])]
        assert total > 0 and done == total, final
        assert between, f"the progress never showed a count between 0 and the total: {seen}"
        check(f"demo job {first} from the library: progress {sorted(seen)} -> succeeded")

        # Its report opens inline, with its results summary beside it.
        page.wait_for_selector("#results-summary")
        frame = page.frame_locator("#report-frame")
        heading = frame.locator("h1").first
        heading.wait_for(timeout=30_000)
        assert heading.inner_text().strip(), "the report has a title"
        check(f"report of job {first} opens inline: {heading.inner_text().strip()!r}")
        # A sandboxed frame is drawn in its own process: a full-page capture leaves it blank,
        # a tall viewport does not.
        page.set_viewport_size({"width": 1280, "height": 2200})
        page.wait_for_timeout(1500)
        page.screenshot(path=f"{SHOTS}/job.png")
        page.set_viewport_size({"width": 1280, "height": 900})

        # After the two more runs the machine's history shows three runs and their trend.
        for other in others:
            assert wait_ended(OPEN, other)["state"] == "succeeded", other
        page.goto(OPEN + "/#/machines")
        page.wait_for_selector("main[data-page='machines'] a[href^='#/machines/']")
        page.locator("main a[href^='#/machines/']").first.click()
        page.wait_for_selector("#trend-plots svg[data-parameter]", timeout=60_000)
        heading = page.locator("h2", has_text="Trend over").inner_text()
        assert "Trend over 3" in heading, heading
        plots = page.locator("#trend-plots svg[data-parameter]").count()
        dots = page.locator("#trend-plots svg[data-parameter]").first.locator("circle.dot").count()
        assert plots > 0 and dots == 3, (plots, dots)
        # The daemon's [history] tolerances (m and rad) give the parameters a tolerance band.
        bands = page.locator("#trend-plots svg[data-parameter] rect.band[data-band-source='tolerance']")
        assert bands.count() > 0, "no tolerance band drawn"
        band_title = bands.first.locator("title").text_content()
        assert "tolerance band (tolerance)" in band_title and "± 0.50 µ" in band_title, band_title
        assert page.locator("#compare-result tbody tr").count() > 0
        z = page.locator("#compare-result tbody tr td:last-child").first.inner_text()
        assert float(z) != 0.0, f"two runs with different noise compare equal: z {z}"
        machine_url = page.url
        check(f"machine with 3 runs: trend of {plots} parameters drawn, 3 runs each, "
              f"{bands.count()} tolerance bands, compare table")
        shot(page, "machine")

        # A HIL run uploaded as TOML, its operator prompts answered by clicking Continue.
        page.goto(OPEN + "/#/jobs")
        page.set_input_files("#plan-file", HIL_PLAN)
        page.click("#submit-upload")
        hil = job_id_of(page)
        answered = []
        deadline = time.time() + JOB_TIMEOUT_S
        while time.time() < deadline:
            if job(OPEN, hil)["state"] in ENDED:
                break
            _, prompts = api(OPEN, "/v1/prompts")
            waiting = [q for q in prompts if q["id"] not in answered]
            if not waiting:
                time.sleep(0.2)
                continue
            prompt = waiting[0]
            assert prompt["job"] == hil, prompt
            if not answered:
                # The first on the Prompts page: the instruction, the layout, one big button.
                page.goto(OPEN + "/#/prompts")
                button = page.locator(f"[data-ack='{prompt['id']}']")
                button.wait_for()
                assert page.locator("svg circle.station.next").count() == 1
                assert page.locator("svg rect.travel").count() == 1
                assert page.locator("#prompt-banner").is_visible()
                shot(page, "prompts")
                button.click()
            else:
                # The others from the banner, on whatever page is open.
                banner = page.locator(
                    f"#banner-continue[data-prompt='{prompt['id']}']:not([disabled])"
                )
                banner.wait_for(timeout=30_000)
                banner.click()
            answered.append(prompt["id"])
            gone = time.time() + 30
            while any(q["id"] == prompt["id"] for q in api(OPEN, "/v1/prompts")[1]):
                assert time.time() < gone, f"prompt {prompt['id']} still waits after Continue"
                time.sleep(0.1)
            if len(answered) == 2:
                # Mid-run: the Now page with the devices and the live readings.
                page.goto(OPEN + "/#/now")
                length = "svg.plot[aria-label$='length']"
                page.wait_for_selector(f"{length} polyline", timeout=60_000)
                page.wait_for_selector("main[data-page='now'] progress")
                page.wait_for_timeout(2500)
                plot = page.locator(length).first
                drawn = int(plot.get_attribute("data-samples"))
                span = float(plot.get_attribute("data-span-s"))
                received = int(plot.get_attribute("data-received"))
                # The 1 kHz tracer's samples arrive from the daemon's stream, not once a second.
                assert drawn > 1 and span > 0 and drawn / span > 10, (drawn, span, received)
                shot(page, "now")
                check(f"Now page: running job, devices and live plots of the tracer "
                      f"({drawn} samples drawn over {span:.1f} s, {received} received)")
        final = wait_ended(OPEN, hil)
        assert final["state"] == "succeeded", final
        assert len(answered) == 5, answered
        check(f"HIL job {hil}: {len(answered)} prompts answered by clicking Continue, succeeded")

        # No prompt waits any more: no banner.
        page.wait_for_selector("#prompt-banner", state="hidden", timeout=10_000)
        page.goto(OPEN + "/#/schedules")
        row = page.locator("main tr", has_text="nightly")
        row.wait_for()
        assert "30 2 * * *" in row.inner_text()
        check("Schedules page lists the nightly schedule with its next run")
        shot(page, "schedules")
        page.goto(OPEN + "/#/jobs")
        page.wait_for_selector(f"tr[data-job='{hil}']")
        shot(page, "jobs")
        assert not errors, errors

        # A phone: nothing scrolls sideways on any page.
        phone = browser.new_context(viewport={"width": 360, "height": 740}, is_mobile=True)
        small = phone.new_page()
        for route in ["#/now", "#/prompts", "#/jobs", f"#/jobs/{first}", "#/schedules",
                      "#/machines", machine_url.split("/", 3)[3]]:
            small.goto(OPEN + "/" + route.lstrip("/"))
            small.wait_for_selector("main[data-page]")
            no_sideways_scroll(small, route)
            if route == "#/jobs":
                shot(small, "phone-jobs")
        check("phone viewport (360 px): no page scrolls sideways")

        # The token daemon: the page asks for the token, the cookie holds no token.
        guarded = browser.new_context(viewport={"width": 1280, "height": 900})
        page = guarded.new_page()
        page.goto(GUARDED + "/#/jobs")
        page.wait_for_selector("dialog#login[open]")
        assert page.locator("#plan-select").count() == 0
        shot(page, "login")
        page.fill("#login-token", "not-the-token-at-all")
        page.click("#login button[type=submit]")
        # A locator, not wait_for_function: that polls with eval, which the page's CSP forbids.
        page.locator("#login-error").filter(has_text=re.compile(r"\S")).wait_for()
        page.fill("#login-token", TOKEN)
        page.click("#login button[type=submit]")
        page.wait_for_selector("dialog#login", state="hidden")
        page.wait_for_selector("#plan-select")
        cookie = [c for c in guarded.cookies() if c["name"] == "geocal_session"]
        assert len(cookie) == 1 and cookie[0]["httpOnly"] and cookie[0]["sameSite"] == "Strict", cookie
        assert TOKEN not in cookie[0]["value"]
        assert "geocal_session" not in page.evaluate("document.cookie")
        assert api(GUARDED, "/v1/jobs")[0] == 401
        check("token daemon: the page demands the login; HttpOnly SameSite=Strict cookie")

        # Another origin's page POSTs to both daemons: refused, nothing submitted.
        for base, token in [(GUARDED, TOKEN), (OPEN, None)]:
            before = len(api(base, "/v1/jobs", token=token)[1])
            page.goto(f"{hostile_url}/?to={base}/v1/plans/demo.toml/submit")
            page.wait_for_url(f"{base}/v1/plans/demo.toml/submit")
            text = page.locator("body").inner_text()
            assert "another web origin" in text, text
            after = len(api(base, "/v1/jobs", token=token)[1])
            assert before == after, (base, before, after)
        status, body = api(GUARDED, "/v1/prompts/1/ack", "POST", TOKEN,
                           {"Origin": "http://evil.example"})
        assert status == 403, (status, body)
        status, _ = api(GUARDED, "/v1/prompts/1/ack", "POST", TOKEN,
                        {"Origin": GUARDED})
        assert status == 404, status
        check("cross-origin POSTs refused (403) on both daemons, nothing submitted")
        browser.close()
    print("console: all checks passed", flush=True)


if __name__ == "__main__":
    main()
