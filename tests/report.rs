//! `geocal report` for every example configuration in `config/`, checked in a real headless
//! browser (Debian's `chromium`, installed by `.ci/run`): the page loads with no console
//! error, every expected plot is an SVG with data (polylines, circles or polygons, not only
//! axes), and printing it to PDF gives no more pages than docs/report.md states. The
//! Markdown report of the same run carries the same sections, with each plot as an SVG file.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

/// (config, plots the report must hold, most A4 pages in print: docs/report.md).
const CASES: &[(&str, &[&str], usize)] = &[
    (
        "demo-multilateration.toml",
        &[
            "errors-x",
            "errors-y",
            "errors-z",
            "volumetric-arrows",
            "station-layout",
            "diagnosis-residuals",
        ],
        6,
    ),
    (
        "rotary-tracer.toml",
        &["step-angle-errors", "volumetric-arrows", "station-layout"],
        4,
    ),
    ("rotary-sphere.toml", &["motion-errors"], 4),
    ("probe-install.toml", &["parameter-changes"], 3),
    ("hexapod.toml", &["hinge-corrections"], 3),
];

fn geocal(args: &[&std::ffi::OsStr]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_geocal"))
        .args(args)
        .stdin(Stdio::null())
        .output()
        .expect("run geocal");
    assert!(
        out.status.success(),
        "geocal {:?} failed: {}",
        args,
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// The browser, or a failure that says how to get it: CI installs it, a silent skip would
/// hide that the acceptance check did not run.
fn chromium() -> PathBuf {
    for name in ["chromium", "chromium-browser"] {
        for dir in std::env::split_paths(&std::env::var_os("PATH").unwrap_or_default()) {
            let candidate = dir.join(name);
            if candidate.is_file() {
                return candidate;
            }
        }
    }
    panic!(
        "tests/report.rs needs a headless browser: `chromium` is not on PATH \
         (Debian: apt-get install -y chromium; .ci/run installs it)"
    );
}

/// Runs headless chromium on `page` with `extra` arguments; returns (stdout, stderr).
fn browse(page: &Path, extra: &[String]) -> (String, String) {
    let profile = tempfile::tempdir().expect("tempdir");
    let out = Command::new(chromium())
        .args([
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--no-first-run",
            "--enable-logging=stderr",
            "--v=0",
        ])
        .arg(format!("--user-data-dir={}", profile.path().display()))
        .args(extra)
        .arg(format!("file://{}", page.display()))
        .stdin(Stdio::null())
        .output()
        .expect("run chromium");
    assert!(
        out.status.success(),
        "chromium on {} failed: {}",
        page.display(),
        String::from_utf8_lossy(&out.stderr)
    );
    (
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// Console messages of the page as chromium logs them (`CONSOLE(n)` lines, uncaught errors).
fn console_errors(stderr: &str) -> Vec<&str> {
    stderr
        .lines()
        .filter(|l| l.contains(":CONSOLE") || l.contains("Uncaught"))
        .collect()
}

/// The page as the browser built it: its DOM after load.
fn dom(page: &Path) -> String {
    let (dom, stderr) = browse(page, &["--dump-dom".to_string()]);
    let errors = console_errors(&stderr);
    assert!(
        errors.is_empty(),
        "{}: console errors {errors:#?}",
        page.display()
    );
    dom
}

/// The content of `<figure data-plot="id">…</figure>` in the DOM.
fn figure<'a>(dom: &'a str, id: &str) -> Option<&'a str> {
    let start = dom.find(&format!("<figure data-plot=\"{id}\""))?;
    let end = dom[start..].find("</figure>")?;
    Some(&dom[start..start + end])
}

/// Data marks of a plotters SVG: series are polylines, circles and polygons; the axes and
/// the mesh are lines and text.
fn data_marks(svg: &str) -> usize {
    ["<polyline", "<circle", "<polygon"]
        .iter()
        .map(|m| svg.matches(m).count())
        .sum()
}

fn pdf_pages(pdf: &[u8]) -> usize {
    let needle = b"/Type /Page";
    pdf.windows(needle.len() + 1)
        .filter(|w| &w[..needle.len()] == needle && w[needle.len()] != b's')
        .count()
}

fn print_pages(page: &Path, dir: &Path) -> usize {
    let pdf = dir.join("report.pdf");
    browse(
        page,
        &[
            "--no-pdf-header-footer".to_string(),
            format!("--print-to-pdf={}", pdf.display()),
        ],
    );
    pdf_pages(&std::fs::read(&pdf).expect("the printed PDF"))
}

#[test]
fn the_console_check_sees_a_console_error() {
    let dir = tempfile::tempdir().expect("tempdir");
    let page = dir.path().join("bad.html");
    std::fs::write(
        &page,
        "<!DOCTYPE html><html><body><script>console.error('broken');</script></body></html>",
    )
    .expect("write page");
    let (_, stderr) = browse(&page, &["--dump-dom".to_string()]);
    assert!(
        !console_errors(&stderr).is_empty(),
        "a page calling console.error must be caught: {stderr}"
    );
}

#[test]
fn reports_of_every_example_config_load_draw_and_print() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    for (config, plots, max_pages) in CASES {
        let dir = tempfile::tempdir().expect("tempdir");
        let run = dir.path().join("run");
        geocal(&[
            "run".as_ref(),
            root.join("config").join(config).as_os_str(),
            "--out".as_ref(),
            run.as_os_str(),
        ]);
        // Markdown first: the diagnosis section is rendered alike, and its plot is costly.
        let md = dir.path().join("md").join("report.md");
        std::fs::create_dir_all(md.parent().expect("dir")).expect("md dir");
        geocal(&[
            "report".as_ref(),
            run.as_os_str(),
            "--format".as_ref(),
            "md".as_ref(),
            "--out".as_ref(),
            md.as_os_str(),
        ]);
        let text = std::fs::read_to_string(&md).expect("report.md");
        assert!(
            text.contains("## Summary"),
            "{config}: Markdown without summary"
        );
        for plot in plots.iter().filter(|p| **p != "diagnosis-residuals") {
            let file = format!("report-{plot}.svg");
            assert!(
                text.contains(&format!("]({file})")),
                "{config}: md lacks {file}"
            );
            let svg = std::fs::read_to_string(md.with_file_name(&file)).expect("plot file");
            assert!(data_marks(&svg) > 0, "{config}: {file} has no data");
        }
        if plots.contains(&"diagnosis-residuals") {
            let diagnosis = geocal(&[
                "diagnose".as_ref(),
                run.join("session.mcap").as_os_str(),
                "--json".as_ref(),
            ]);
            std::fs::write(run.join("diagnosis.json"), diagnosis).expect("diagnosis.json");
        }
        let page = dir.path().join("report.html");
        geocal(&[
            "report".as_ref(),
            run.as_os_str(),
            "--out".as_ref(),
            page.as_os_str(),
        ]);
        let html = std::fs::read_to_string(&page).expect("report.html");
        for fetch in ["src=\"http", "href=\"http", "url(http", "<script", "<link"] {
            assert!(!html.contains(fetch), "{config}: the page fetches: {fetch}");
        }

        let dom = dom(&page);
        for section in ["id=\"header\"", "id=\"summary\""] {
            assert!(dom.contains(section), "{config}: no {section} section");
        }
        // The standards' sections of the network kinds: the ISO 230-2 figures of each pass,
        // and the budget with its contributors.
        if config.contains("rotary-tracer") {
            for text in [
                "id=\"iso230-2\"",
                "axis c: ",
                "id=\"rotary-tracer-uncertainty\"",
                "step-angle error of table c",
                "reflector/probe",
            ] {
                assert!(dom.contains(text), "{config}: no {text}");
            }
        }
        if config.contains("multilateration") {
            for text in [
                "id=\"iso230-2\"",
                "axis x (target ",
                "id=\"uncertainty\"",
                "material temperature sensor",
            ] {
                assert!(dom.contains(text), "{config}: no {text}");
            }
        }
        assert!(
            dom.contains("<dt>machine</dt>"),
            "{config}: header without machine"
        );
        assert!(
            dom.contains("Instruments"),
            "{config}: header without instruments"
        );
        for plot in *plots {
            let svg = figure(&dom, plot)
                .unwrap_or_else(|| panic!("{config}: plot `{plot}` missing from the page"));
            assert!(
                svg.contains("<svg"),
                "{config}: plot `{plot}` is not an SVG"
            );
            assert!(
                data_marks(svg) > 0,
                "{config}: plot `{plot}` has axes but no data"
            );
        }
        if config.contains("multilateration") || config.contains("rotary-tracer") {
            iso_tables_hold_the_figures(&dom, &run);
        }
        if config.contains("multilateration") {
            summary_holds_the_largest_errors(&dom, &run);
            diagnosis_table_holds_the_candidates(&dom, &run);
            unidentifiable_functions_are_named_not_drawn(&dom, &run);
        }
        screenshot(&page, config);
        let pages = print_pages(&page, dir.path());
        assert!(
            (1..=*max_pages).contains(&pages),
            "{config}: printed to {pages} A4 pages, docs/report.md allows {max_pages}"
        );
        eprintln!(
            "{config}: {} plots, {pages} pages (≤ {max_pages})",
            plots.len()
        );
    }
}

/// Where the screenshots of the reports' first screens go (docs/report.md: the one of the
/// demo is `docs/report-first-page.png`).
fn screenshot_dir() -> PathBuf {
    Path::new(env!("CARGO_TARGET_TMPDIR")).join("report-screenshots")
}

/// A screenshot of the page's first A4 screen (794 × 1123 CSS px) as PNG.
fn screenshot(page: &Path, config: &str) {
    let dir = screenshot_dir();
    std::fs::create_dir_all(&dir).expect("screenshot dir");
    let png = dir.join(config.replace(".toml", ".png"));
    browse(
        page,
        &[
            format!("--screenshot={}", png.display()),
            "--window-size=794,1123".to_string(),
            "--hide-scrollbars".to_string(),
        ],
    );
    let bytes = std::fs::read(&png).expect("the screenshot");
    assert!(
        bytes.starts_with(b"\x89PNG") && bytes.len() > 10_000,
        "{}: not a PNG of a page ({} bytes)",
        png.display(),
        bytes.len()
    );
    eprintln!("screenshot: {}", png.display());
}

/// The `<section id="id">…</section>` of the DOM.
fn section<'a>(dom: &'a str, id: &str) -> &'a str {
    let start = dom
        .find(&format!("<section id=\"{id}\">"))
        .unwrap_or_else(|| panic!("no section {id}"));
    let end = dom[start..].find("</section>").expect("section end");
    &dom[start..start + end]
}

/// Every table row of `html` as its cells' text (`<td>` and `<th>`).
fn rows(html: &str) -> Vec<Vec<String>> {
    html.split("<tr>")
        .skip(1)
        .map(|row| {
            let row = row.split("</tr>").next().unwrap_or("");
            row.split("<t")
                .skip(1)
                .filter_map(|cell| {
                    let text = cell.split_once('>')?.1;
                    let text = text.split("</t").next().unwrap_or("");
                    Some(
                        text.replace("&lt;", "<")
                            .replace("&gt;", ">")
                            .replace("&quot;", "\"")
                            .replace("&#39;", "'")
                            .replace("&amp;", "&"),
                    )
                })
                .collect()
        })
        .collect()
}

/// The ISO 230-2 section is a table per axis, no `<pre>`, its cells the figures the
/// evaluation of the results and the session gives (docs/iso230-2.md).
fn iso_tables_hold_the_figures(dom: &str, run: &Path) {
    let html = section(dom, "iso230-2");
    assert!(!html.contains("<pre"), "ISO 230-2 section with <pre>");
    let session =
        geocal::session::reader::read_session(&run.join("session.mcap")).expect("session");
    let results = geocal::kinds::registry::solve_session(&session, &Default::default())
        .expect("solve the session");
    let iso = geocal::evaluate::of_results(&results, &session).expect("ISO 230-2");
    assert_eq!(
        html.matches("<table").count(),
        iso.axes.len(),
        "a table per axis"
    );
    assert_eq!(
        html.matches("class=\"badge ").count(),
        iso.axes.len(),
        "a badge per axis"
    );
    let cells = rows(html);
    for axis in &iso.axes {
        let scale = match axis.evaluation.axis_type {
            geocal::evaluate::iso230_2::AxisType::Linear => 1e6,
            geocal::evaluate::iso230_2::AxisType::Rotary => 180.0 / std::f64::consts::PI * 3600.0,
        };
        let v = |x: Option<f64>| x.map_or("—".to_string(), |x| format!("{:.3}", x * scale));
        let f = axis.evaluation.figures();
        let mut want = Vec::new();
        if let Some(u) = &f.up {
            want.push([
                "↑".into(),
                v(Some(u.systematic_error)),
                v(None),
                v(u.repeatability),
                v(None),
                v(u.accuracy),
            ]);
        }
        if let Some(b) = &f.bidirectional {
            want.push([
                "↕".into(),
                v(Some(b.systematic_error)),
                v(Some(b.mean_error)),
                v(b.repeatability),
                v(Some(b.reversal)),
                v(b.accuracy),
            ]);
        }
        assert!(!want.is_empty(), "axis {} without figures", axis.axis);
        for row in want {
            assert!(
                cells.iter().any(|c| c[..] == row[..]),
                "axis {}: no row {row:?} in {cells:?}",
                axis.axis
            );
        }
        // Each departure from the standard is a footnote, given once.
        for why in &axis.evaluation.not_per_iso_230_2 {
            assert_eq!(
                html.matches(&format!("<li>not per ISO 230-2: {why}"))
                    .count(),
                1,
                "footnote `{why}`"
            );
        }
    }
}

/// The diagnosis: a verdict badge first, a table whose rows hold each effect's figures from
/// diagnosis.json, then the residual plot; no `<pre>`.
fn diagnosis_table_holds_the_candidates(dom: &str, run: &Path) {
    let html = section(dom, "diagnosis");
    assert!(!html.contains("<pre"), "diagnosis section with <pre>");
    let d: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("diagnosis.json")).expect("json"))
            .expect("diagnosis.json");
    let badge = html.find("class=\"badge ").expect("a verdict badge");
    let table = html.find("<table").expect("the candidates table");
    let plot = html
        .find("<figure data-plot=\"diagnosis-residuals\"")
        .expect("the residual plot");
    assert!(
        badge < table && table < plot,
        "verdict, table, plot in that order"
    );
    let verdict = &html[badge..badge + html[badge..].find("</span>").expect("badge end")];
    for effect in d["selected"].as_array().expect("selected") {
        let effect = effect.as_str().expect("name");
        assert!(
            verdict.contains(effect),
            "verdict without {effect}: {verdict}"
        );
    }
    if d["selected"].as_array().is_some_and(|s| s.is_empty()) && d["unexplained"] == false {
        assert!(
            verdict.contains("consistent with the noise model") || verdict.contains("no effect"),
            "{verdict}"
        );
    }
    let cells = rows(&html[table..plot]);
    let candidates = d["candidates"].as_array().expect("candidates");
    assert!(!candidates.is_empty());
    for c in candidates {
        let effect = c["effect"].as_str().expect("effect");
        let figures = |c: &serde_json::Value| {
            let n = |k: &str| c[k].as_f64().expect("number");
            vec![
                format!("{:.1}", n("chi2_drop")),
                format!("{:.1e}", n("p_value")),
                format!("{:.1}", n("bic_delta")),
                format!("{:.1}", n("heldout_rms_after_m") * 1e9),
            ]
        };
        let row = cells
            .iter()
            .find(|r| r.first().map(String::as_str) == Some(effect))
            .unwrap_or_else(|| panic!("no row of {effect}"));
        assert!(
            candidates
                .iter()
                .filter(|o| o["effect"] == c["effect"])
                .any(|o| row[3..7] == figures(o)[..]
                    && row[7].starts_with(o["status"].as_str().unwrap_or("?"))),
            "{effect}: row {row:?} holds none of its candidates' figures and outcome"
        );
    }
}

/// The summary box: a tolerance verdict, the diagnosis's, and the largest errors, each the
/// largest |value| of its function in results.json (those the 20 °C normalisation does not
/// change: straightness and angles), lengths in decreasing order.
fn summary_holds_the_largest_errors(dom: &str, run: &Path) {
    let html = section(dom, "summary");
    assert!(
        html.matches("class=\"badge ").count() >= 2,
        "tolerance and diagnosis badges"
    );
    assert!(
        html.contains("diagnosis: "),
        "no diagnosis verdict in the summary"
    );
    let results: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("results.json")).expect("json"))
            .expect("results.json");
    let rows: Vec<Vec<String>> = rows(html)
        .into_iter()
        .filter(|r| r.len() == 6 && r[1].contains(" = "))
        .collect();
    assert!(rows.len() >= 3, "fewer than three largest errors: {rows:?}");
    let mut lengths = Vec::new();
    let mut checked = 0;
    for row in &rows {
        let (name, axis) = (&row[0], row[1].split(" = ").next().expect("axis"));
        let f = &results["geometric_errors"]["axes"][axis]["errors"][name.as_str()];
        let unit = f["unit"].as_str().expect("unit");
        let (scale, shown) = if unit == "rad" {
            (180.0 / std::f64::consts::PI * 3600.0, "″")
        } else {
            (1e6, "µm")
        };
        let value: f64 = row[2]
            .split(' ')
            .next()
            .expect("value")
            .parse()
            .expect("number");
        if shown == "µm" {
            lengths.push(value.abs());
        }
        assert!(row[2].ends_with(shown), "{row:?}");
        let positioning =
            name.as_str() == format!("E{}{}", axis.to_uppercase(), axis.to_uppercase());
        if positioning {
            continue;
        }
        let largest = f["values"]
            .as_array()
            .expect("values")
            .iter()
            .filter_map(|v| v.as_f64())
            .max_by(|a, b| a.abs().total_cmp(&b.abs()))
            .expect("a value");
        assert_eq!(
            row[2],
            format!("{:.3} {shown}", largest * scale),
            "{name} along {axis}"
        );
        checked += 1;
    }
    assert!(checked > 0, "no row checked against results.json: {rows:?}");
    assert!(
        lengths.windows(2).all(|w| w[0] >= w[1]),
        "lengths not in order: {lengths:?}"
    );
}

/// The error functions the plan cannot identify: named in one line, not drawn.
fn unidentifiable_functions_are_named_not_drawn(dom: &str, run: &Path) {
    let results: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("results.json")).expect("json"))
            .expect("results.json");
    let mut names = Vec::new();
    for (_, axis) in results["geometric_errors"]["axes"]
        .as_object()
        .expect("axes")
    {
        for (name, f) in axis["errors"].as_object().expect("errors") {
            if f["identifiable"] == false && !names.contains(name) {
                names.push(name.clone());
            }
        }
    }
    if names.is_empty() {
        return;
    }
    let line = format!(
        "not identifiable from this plan: {} — see docs/kinematics.md",
        names.join(", ")
    );
    assert!(dom.contains(&line), "no line `{line}`");
    assert!(
        !dom.contains("(not identifiable)"),
        "a non-identifiable function is drawn"
    );
}

/// The closed loop through the command line: the demo calibrated, its SINUMERIK tables
/// (encoder and cross) exported and applied, the same plan run again; the verification run's
/// report shows the tables, before vs after with ±2σ and each verdict, in HTML and Markdown,
/// within its page limit (docs/report.md). A before-results file that is gone or another
/// one is a message in the report, not a failure.
#[test]
fn verification_report_shows_before_and_after() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let dir = tempfile::tempdir().expect("tempdir");
    let before = dir.path().join("before");
    let demo = root.join("config").join("demo-multilateration.toml");
    geocal(&[
        "run".as_ref(),
        demo.as_os_str(),
        "--out".as_ref(),
        before.as_os_str(),
    ]);
    let tables = dir.path().join("tables");
    geocal(&[
        "compensate".as_ref(),
        before.join("results.json").as_os_str(),
        "--format".as_ref(),
        "sinumerik".as_ref(),
        "--out".as_ref(),
        tables.as_os_str(),
    ]);
    let sidecar = std::fs::read_to_string(tables.join("geocal-source.json")).expect("sidecar");
    assert!(sidecar.contains("results_sha256"), "{sidecar}");
    let config = dir.path().join("verify.toml");
    std::fs::write(
        &config,
        format!(
            "{}noise_seed = 4242\ncompensation = [\n\
             {{ format = \"sinumerik\", file = \"tables/eec.ini\", axis = \"x\" }},\n\
             {{ format = \"sinumerik\", file = \"tables/eec.ini\", axis = \"y\" }},\n\
             {{ format = \"sinumerik\", file = \"tables/eec.ini\", axis = \"z\" }},\n\
             {{ format = \"sinumerik\", file = \"tables/cec.ini\" }},\n]\n",
            std::fs::read_to_string(&demo).expect("demo config")
        ),
    )
    .expect("write config");
    let after = dir.path().join("after");
    geocal(&[
        "run".as_ref(),
        config.as_os_str(),
        "--out".as_ref(),
        after.as_os_str(),
    ]);

    // Markdown: the section, its tables and the plot file with data.
    let md = dir.path().join("md").join("report.md");
    std::fs::create_dir_all(md.parent().expect("dir")).expect("md dir");
    let report_md = |extra: &[&std::ffi::OsStr]| {
        let mut args: Vec<&std::ffi::OsStr> = vec![
            "report".as_ref(),
            after.as_os_str(),
            "--format".as_ref(),
            "md".as_ref(),
            "--out".as_ref(),
            md.as_os_str(),
        ];
        args.extend_from_slice(extra);
        geocal(&args);
        std::fs::read_to_string(&md).expect("report.md")
    };
    let text = report_md(&[]);
    let verification = &text[text
        .find("## Verification run")
        .expect("verification section")..];
    println!("{}", &verification[..verification.len().min(4000)]);
    for expect in [
        "$AN_CEC[0]",
        "$AA_ENC_COMP[0,…,X1]",
        "| EXX |",
        "EXY − EC0Y·y",
        "9 of 9 compensated errors within 2σ + interpolation error: pass",
    ] {
        assert!(verification.contains(expect), "Markdown lacks `{expect}`");
    }
    // Every compared error's row ends with its verdict; the numbers behind it are the table's.
    let rows: Vec<&str> = verification
        .lines()
        .filter(|l| l.ends_with("| pass |") || l.ends_with("| FAIL |"))
        .collect();
    assert_eq!(rows.len(), 9, "{rows:#?}");
    for row in &rows {
        let cells: Vec<f64> = row
            .split('|')
            .filter_map(|c| c.trim().parse().ok())
            .collect();
        // RMS before, max before, RMS after, max after, RMS σ, interpolation, bound.
        assert_eq!(cells.len(), 7, "{row}");
        assert!(cells[2] <= cells[6] && cells[2] < 0.5 * cells[0], "{row}");
        assert!(
            (cells[6] - (2.0 * cells[4] + cells[5])).abs() < 2e-3,
            "{row}"
        );
    }
    // Nine panels, each with data: before, after and the table; after and its bound.
    // Each panel's title (a line of its own in plotters' SVG) carries its verdict or bound.
    for (plot, title) in [
        ("verification-before-after", ": pass"),
        ("verification-after", " µm"),
    ] {
        let file = format!("report-{plot}.svg");
        assert!(
            verification.contains(&format!("]({file})")),
            "md lacks {file}"
        );
        let svg = std::fs::read_to_string(md.with_file_name(&file)).expect("plot file");
        assert!(data_marks(&svg) >= 9 * 3, "{plot}: {}", data_marks(&svg));
        let titles = svg
            .lines()
            .filter(|l| l.ends_with(title) && (l.starts_with('E') || l.contains(", bound ")))
            .count();
        assert_eq!(titles, 9, "{plot}: panel titles");
    }

    // HTML in the browser: the section, the plot with data, the page limit.
    let page = dir.path().join("report.html");
    geocal(&[
        "report".as_ref(),
        after.as_os_str(),
        "--out".as_ref(),
        page.as_os_str(),
    ]);
    let dom = dom(&page);
    assert!(
        dom.contains("id=\"verification\""),
        "no verification section"
    );
    for id in ["verification-before-after", "verification-after"] {
        let plot = figure(&dom, id).unwrap_or_else(|| panic!("plot {id} missing"));
        assert!(
            plot.contains("<svg") && data_marks(plot) >= 9 * 3,
            "{id} without data"
        );
    }
    let pages = print_pages(&page, dir.path());
    println!("verification report: {pages} pages");
    assert!(
        (1..=VERIFICATION_MAX_PAGES).contains(&pages),
        "printed to {pages} A4 pages, docs/report.md allows {VERIFICATION_MAX_PAGES}"
    );

    // Another before file: compared, with a note that the tables did not come from it.
    // (The summary lists EXX among the largest errors: the comparison's rows are looked for in
    // the verification section.)
    let section = |text: &str| -> String {
        let start = text
            .find("## Verification run")
            .expect("verification section");
        let rest = &text[start..];
        let end = rest[3..].find("\n## ").map_or(rest.len(), |e| e + 3);
        rest[..end].to_string()
    };
    let text = section(&report_md(&[
        "--before".as_ref(),
        after.join("results.json").as_os_str(),
    ]));
    assert!(
        text.contains("the tables did not come from") && text.contains("| EXX |"),
        "--before with another file"
    );
    // The before results gone: a message in the report, no comparison.
    std::fs::rename(before.join("results.json"), dir.path().join("moved.json")).expect("move");
    let text = section(&report_md(&[]));
    assert!(
        text.contains("are not there") && text.contains("--before RESULTS"),
        "missing before results"
    );
    assert!(
        !text.contains("| EXX |"),
        "no comparison without before results"
    );
    // Changed since the tables were made: refused by its SHA-256.
    let mut changed = std::fs::read_to_string(dir.path().join("moved.json")).expect("moved");
    changed.push('\n');
    std::fs::write(before.join("results.json"), changed).expect("write");
    let text = report_md(&[]);
    assert!(
        text.contains("changed since the tables were made"),
        "changed before results"
    );
    std::fs::rename(dir.path().join("moved.json"), before.join("results.json")).expect("move");

    // LinuxCNC: type 1 tables on x and z, type 0 on y, from the same calibration.
    let linuxcnc = |format: &str, out: &str| {
        geocal(&[
            "compensate".as_ref(),
            before.join("results.json").as_os_str(),
            "--format".as_ref(),
            format.as_ref(),
            "--out".as_ref(),
            dir.path().join(out).as_os_str(),
        ]);
    };
    linuxcnc("linuxcnc-type1", "type1");
    linuxcnc("linuxcnc-type0", "type0");
    let config = dir.path().join("verify-linuxcnc.toml");
    std::fs::write(
        &config,
        format!(
            "{}noise_seed = 4242\ncompensation = [\n\
             {{ format = \"linuxcnc-type1\", file = \"type1/comp-x.txt\", axis = \"x\" }},\n\
             {{ format = \"linuxcnc-type0\", file = \"type0/comp-y.txt\", axis = \"y\" }},\n\
             {{ format = \"linuxcnc-type1\", file = \"type1/comp-z.txt\", axis = \"z\" }},\n]\n",
            std::fs::read_to_string(&demo).expect("demo config")
        ),
    )
    .expect("write config");
    let after_linuxcnc = dir.path().join("after-linuxcnc");
    geocal(&[
        "run".as_ref(),
        config.as_os_str(),
        "--out".as_ref(),
        after_linuxcnc.as_os_str(),
    ]);
    geocal(&[
        "report".as_ref(),
        after_linuxcnc.as_os_str(),
        "--format".as_ref(),
        "md".as_ref(),
        "--out".as_ref(),
        md.as_os_str(),
    ]);
    let text = std::fs::read_to_string(&md).expect("report.md");
    let verification = &text[text
        .find("## Verification run")
        .expect("verification section")..];
    println!("{}", &verification[..verification.len().min(3000)]);
    for expect in [
        "comp-x.txt",
        "comp-y.txt",
        "comp-z.txt",
        "| EXX |",
        "| EYY |",
        "| EZZ |",
    ] {
        assert!(
            verification.contains(expect),
            "LinuxCNC report lacks `{expect}`"
        );
    }
    let verdicts: Vec<&str> = verification
        .lines()
        .filter(|l| l.ends_with("| pass |") || l.ends_with("| FAIL |"))
        .collect();
    assert_eq!(verdicts.len(), 3, "{verdicts:#?}");
    assert!(
        verdicts.iter().all(|l| l.ends_with("| pass |")),
        "{verdicts:#?}"
    );
}

/// The most A4 pages of the demo's verification report (docs/report.md).
const VERIFICATION_MAX_PAGES: usize = 7;
