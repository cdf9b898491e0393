//! One self-contained HTML page from a `Document`: inline CSS (A4 print rules included) and
//! inline SVG, no script and no external resource, so it opens and prints offline.

use std::fmt::Write;

use super::{Block, Document, Plot, Table};

const STYLE: &str = "\
body{font-family:sans-serif;font-size:11pt;color:#222;max-width:190mm;margin:1em auto;padding:0 1em}
h1{font-size:18pt;margin:0 0 .3em}
h2{font-size:14pt;border-bottom:1px solid #999;margin:1.2em 0 .4em}
table{border-collapse:collapse;margin:.4em 0;font-size:9pt}
caption{text-align:left;font-weight:bold;padding:.2em 0}
th,td{border:1px solid #bbb;padding:1px 5px;text-align:right}
th{background:#eee}
td:first-child,th:first-child{text-align:left}
dl{display:grid;grid-template-columns:max-content auto;gap:1px 1em;margin:.4em 0}
dt{font-weight:bold}
dd{margin:0}
figure{margin:.6em 0}
figure svg{width:100%;height:auto}
figcaption{font-size:9pt;color:#444}
pre{font-size:8pt;white-space:pre-wrap;background:#f6f6f6;padding:.4em}
nav ol{columns:2;font-size:10pt}
.badge{display:inline-block;font-weight:bold;font-size:9pt;padding:1px 8px;border-radius:8px;margin:.2em 0}
.badge.good{background:#d8f0d8;color:#185018;border:1px solid #4a4}
.badge.bad{background:#f8dada;color:#701818;border:1px solid #c44}
.badge.neutral{background:#eee;color:#333;border:1px solid #999}
ol.notes{font-size:8.5pt;color:#444;margin:.3em 0;padding-left:1.6em}
section#summary{border:2px solid #555;border-radius:4px;padding:0 .8em .4em;margin:.8em 0}
section#summary h2{border:none}
@page{size:A4;margin:12mm}
@media print{body{max-width:none;margin:0;padding:0;font-size:10pt}nav{display:none}
figure,table,dl{break-inside:avoid}h2{break-after:avoid}}
";

/// The document as one HTML page.
pub fn render(doc: &Document) -> String {
    let mut s = String::new();
    let _ = write!(
        s,
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n\
         <title>{}</title>\n<style>\n{STYLE}</style>\n</head>\n<body>\n<h1>{}</h1>\n",
        escape(&doc.title),
        escape(&doc.title)
    );
    s.push_str("<nav><ol>\n");
    for section in &doc.sections {
        let _ = writeln!(
            s,
            "<li><a href=\"#{}\">{}</a></li>",
            escape(&section.id),
            escape(&section.title)
        );
    }
    s.push_str("</ol></nav>\n");
    for section in &doc.sections {
        let _ = writeln!(
            s,
            "<section id=\"{}\">\n<h2>{}</h2>",
            escape(&section.id),
            escape(&section.title)
        );
        for block in &section.blocks {
            block_html(&mut s, block);
        }
        s.push_str("</section>\n");
    }
    s.push_str("</body>\n</html>\n");
    s
}

fn block_html(s: &mut String, block: &Block) {
    match block {
        Block::Paragraph(text) => {
            let _ = writeln!(s, "<p>{}</p>", escape(text));
        }
        Block::Facts(facts) => {
            s.push_str("<dl>\n");
            for (name, value) in facts {
                let _ = writeln!(s, "<dt>{}</dt><dd>{}</dd>", escape(name), escape(value));
            }
            s.push_str("</dl>\n");
        }
        Block::Table(table) => table_html(s, table),
        Block::Plot(plot) => plot_html(s, plot),
        Block::Preformatted(text) => {
            let _ = writeln!(s, "<pre>{}</pre>", escape(text));
        }
        Block::Badge(tone, text) => {
            let _ = writeln!(
                s,
                "<p><span class=\"badge {}\">{}</span></p>",
                tone.class(),
                escape(text)
            );
        }
        Block::Notes(notes) => {
            s.push_str("<ol class=\"notes\">\n");
            for note in notes {
                let _ = writeln!(s, "<li>{}</li>", escape(note));
            }
            s.push_str("</ol>\n");
        }
    }
}

fn table_html(s: &mut String, table: &Table) {
    s.push_str("<table>\n");
    if !table.caption.is_empty() {
        let _ = writeln!(s, "<caption>{}</caption>", escape(&table.caption));
    }
    s.push_str("<thead><tr>");
    for h in &table.header {
        let _ = write!(s, "<th>{}</th>", escape(h));
    }
    s.push_str("</tr></thead>\n<tbody>\n");
    for row in &table.rows {
        s.push_str("<tr>");
        for c in row {
            let _ = write!(s, "<td>{}</td>", escape(c));
        }
        s.push_str("</tr>\n");
    }
    s.push_str("</tbody>\n</table>\n");
}

fn plot_html(s: &mut String, plot: &Plot) {
    let _ = writeln!(s, "<figure data-plot=\"{}\">", escape(&plot.id));
    // plotters writes a complete document; the XML declaration is not allowed inline.
    let svg = plot.svg.trim_start();
    let svg = match svg.strip_prefix("<?xml") {
        Some(rest) => rest.split_once("?>").map_or(rest, |(_, tail)| tail),
        None => svg,
    };
    s.push_str(svg.trim());
    let _ = writeln!(
        s,
        "\n<figcaption>{}</figcaption>\n</figure>",
        escape(&plot.caption)
    );
}

/// Text for HTML content and attribute values.
pub fn escape(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::document::Section;

    #[test]
    fn text_is_escaped_and_svg_is_inlined_without_its_declaration() {
        let doc = Document {
            title: "a <b> & c".into(),
            sections: vec![Section::new("s", "S").paragraph("x < y").plot(Plot {
                id: "p".into(),
                caption: "cap".into(),
                svg: "<?xml version=\"1.0\"?>\n<svg><path d=\"M0 0\"/></svg>".into(),
            })],
        };
        let html = render(&doc);
        assert!(html.contains("<title>a &lt;b&gt; &amp; c</title>"));
        assert!(html.contains("<p>x &lt; y</p>"));
        assert!(html.contains("<figure data-plot=\"p\">\n<svg><path d=\"M0 0\"/></svg>"));
        assert!(!html.contains("<?xml"));
    }
}
