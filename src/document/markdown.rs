//! The same `Document` as Markdown, for people who diff reports: tables as pipe tables, each
//! plot as an SVG file written beside the report and linked by its relative name.

use std::fmt::Write;

use super::{Block, Document, Table};

/// The Markdown text and the plot files it links to (file name, SVG text).
pub fn render(doc: &Document, plot_prefix: &str) -> (String, Vec<(String, String)>) {
    let mut s = String::new();
    let mut files = Vec::new();
    let _ = writeln!(s, "# {}\n", doc.title);
    for section in &doc.sections {
        let _ = writeln!(s, "## {}\n", section.title);
        for block in &section.blocks {
            match block {
                Block::Paragraph(text) => {
                    let _ = writeln!(s, "{text}\n");
                }
                Block::Facts(facts) => {
                    s.push_str("| | |\n|---|---|\n");
                    for (name, value) in facts {
                        let _ = writeln!(s, "| {} | {} |", pipe(name), pipe(value));
                    }
                    s.push('\n');
                }
                Block::Table(table) => table_md(&mut s, table),
                Block::Plot(plot) => {
                    let name = format!("{plot_prefix}{}.svg", plot.id);
                    let _ = writeln!(s, "![{}]({name})\n", plot.caption.replace(']', ")"));
                    files.push((name, plot.svg.clone()));
                }
                Block::Preformatted(text) => {
                    let _ = writeln!(s, "```\n{}\n```\n", text.trim_end());
                }
                Block::Badge(_, text) => {
                    let _ = writeln!(s, "**[{text}]**\n");
                }
                Block::Notes(notes) => {
                    for (k, note) in notes.iter().enumerate() {
                        let _ = writeln!(s, "{}. {note}", k + 1);
                    }
                    s.push('\n');
                }
            }
        }
    }
    (s, files)
}

fn table_md(s: &mut String, table: &Table) {
    if !table.caption.is_empty() {
        let _ = writeln!(s, "**{}**\n", table.caption);
    }
    let _ = writeln!(
        s,
        "| {} |",
        table
            .header
            .iter()
            .map(|h| pipe(h))
            .collect::<Vec<_>>()
            .join(" | ")
    );
    let _ = writeln!(s, "|{}", "---|".repeat(table.header.len().max(1)));
    for row in &table.rows {
        let _ = writeln!(
            s,
            "| {} |",
            row.iter().map(|c| pipe(c)).collect::<Vec<_>>().join(" | ")
        );
    }
    s.push('\n');
}

/// A cell's text with its pipes escaped.
fn pipe(text: &str) -> String {
    text.replace('|', "\\|").replace('\n', " ")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::document::{Plot, Section};

    #[test]
    fn plots_become_files_and_tables_pipe_tables() {
        let mut t = Table::new("t", &["a", "b|c"]);
        t.row(vec!["1".into(), "2".into()]);
        let doc = Document {
            title: "T".into(),
            sections: vec![Section::new("s", "S").table(t).plot(Plot {
                id: "p1".into(),
                caption: "cap".into(),
                svg: "<svg/>".into(),
            })],
        };
        let (md, files) = render(&doc, "report-");
        assert!(md.contains("| a | b\\|c |\n|---|---|\n| 1 | 2 |"));
        assert!(md.contains("![cap](report-p1.svg)"));
        assert_eq!(
            files,
            vec![("report-p1.svg".to_string(), "<svg/>".to_string())]
        );
    }
}
