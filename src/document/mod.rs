//! The report's document model: a title and a list of sections made of paragraphs, key/value
//! lists, tables and SVG plots, rendered to HTML (`html`) and Markdown (`markdown`) alike.
//! Kinds build their sections from their results with it; `plots` draws the SVG figures.

pub mod html;
pub mod markdown;
pub mod plots;

/// A whole report.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Document {
    pub title: String,
    pub sections: Vec<Section>,
}

/// One section: an anchor id (unique in the document), a heading and its content.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Section {
    pub id: String,
    pub title: String,
    pub blocks: Vec<Block>,
}

impl Section {
    pub fn new(id: &str, title: &str) -> Section {
        Section {
            id: id.to_string(),
            title: title.to_string(),
            blocks: Vec::new(),
        }
    }

    pub fn paragraph(mut self, text: impl Into<String>) -> Section {
        self.blocks.push(Block::Paragraph(text.into()));
        self
    }

    pub fn facts(mut self, facts: Vec<(String, String)>) -> Section {
        self.blocks.push(Block::Facts(facts));
        self
    }

    pub fn table(mut self, table: Table) -> Section {
        self.blocks.push(Block::Table(table));
        self
    }

    pub fn plot(mut self, plot: Plot) -> Section {
        self.blocks.push(Block::Plot(plot));
        self
    }

    /// A verdict shown as a coloured badge (a bold bracketed word in Markdown).
    pub fn badge(mut self, tone: Tone, text: impl Into<String>) -> Section {
        self.blocks.push(Block::Badge(tone, text.into()));
        self
    }

    /// Numbered notes, each shown once (a small ordered list).
    pub fn notes(mut self, notes: Vec<String>) -> Section {
        if !notes.is_empty() {
            self.blocks.push(Block::Notes(notes));
        }
        self
    }

    pub fn preformatted(mut self, text: impl Into<String>) -> Section {
        self.blocks.push(Block::Preformatted(text.into()));
        self
    }

    /// Every plot of the section, in order.
    pub fn plots(&self) -> impl Iterator<Item = &Plot> {
        self.blocks.iter().filter_map(|b| match b {
            Block::Plot(p) => Some(p),
            _ => None,
        })
    }
}

#[derive(Debug, Clone, PartialEq)]
pub enum Block {
    Paragraph(String),
    /// Name / value pairs (a definition list in HTML, a two-column table in Markdown).
    Facts(Vec<(String, String)>),
    Table(Table),
    Plot(Plot),
    /// Text shown as is, in a fixed-width font.
    Preformatted(String),
    /// A verdict: its tone colours it.
    Badge(Tone, String),
    /// Numbered footnotes; cells and paragraphs refer to them as ¹, ², …
    Notes(Vec<String>),
}

/// How a verdict reads: met, not met, or neither (not decided, not applicable).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Tone {
    Good,
    Bad,
    Neutral,
}

impl Tone {
    pub fn class(self) -> &'static str {
        match self {
            Tone::Good => "good",
            Tone::Bad => "bad",
            Tone::Neutral => "neutral",
        }
    }
}

/// The footnote mark of note `n` (1-based): ¹, ², … then [n].
pub fn note_mark(n: usize) -> String {
    const SUPERSCRIPTS: [char; 10] = ['⁰', '¹', '²', '³', '⁴', '⁵', '⁶', '⁷', '⁸', '⁹'];
    n.to_string()
        .chars()
        .map(|c| c.to_digit(10).map_or(c, |d| SUPERSCRIPTS[d as usize]))
        .collect()
}

/// A table of already formatted cells (units in the header).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Table {
    pub caption: String,
    pub header: Vec<String>,
    pub rows: Vec<Vec<String>>,
}

impl Table {
    pub fn new(caption: &str, header: &[&str]) -> Table {
        Table {
            caption: caption.to_string(),
            header: header.iter().map(|h| h.to_string()).collect(),
            rows: Vec::new(),
        }
    }

    pub fn row(&mut self, cells: Vec<String>) {
        self.rows.push(cells);
    }
}

/// An SVG figure: `id` names it (a `data-plot` attribute in HTML, the file name beside a
/// Markdown report), `svg` is a complete `<svg>` document.
#[derive(Debug, Clone, PartialEq)]
pub struct Plot {
    pub id: String,
    pub caption: String,
    pub svg: String,
}

impl Document {
    /// Every plot of the document, in order.
    pub fn plots(&self) -> impl Iterator<Item = &Plot> {
        self.sections.iter().flat_map(|s| s.plots())
    }
}

/// What a plan kind contributes to a report: the few numbers that matter (the summary) and
/// its own sections, in order.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct KindReport {
    pub summary: Vec<(String, String)>,
    pub sections: Vec<Section>,
}

impl KindReport {
    /// A kind without report sections of its own: its results JSON, shown as it is.
    pub fn raw(kind: &str, results: &serde_json::Value) -> KindReport {
        let text = serde_json::to_string_pretty(results).unwrap_or_default();
        KindReport {
            summary: Vec::new(),
            sections: vec![Section::new("results", &format!("{kind} results")).preformatted(text)],
        }
    }
}

/// The kind's results type from its results.json, with an error naming what did not fit.
pub fn results_of<T: serde::de::DeserializeOwned>(
    kind: &str,
    results: &serde_json::Value,
) -> anyhow::Result<T> {
    serde_json::from_value(results.clone())
        .map_err(|e| anyhow::anyhow!("results of kind `{kind}` do not match its format: {e}"))
}

/// Micrometres from metres, for display.
pub fn um(m: f64) -> f64 {
    m * 1e6
}

/// Arcseconds from radians, for display.
pub fn arcsec(rad: f64) -> f64 {
    rad.to_degrees() * 3600.0
}

/// A number for a table cell: fixed decimals, "—" when missing or not finite.
pub fn cell(value: Option<f64>, decimals: usize) -> String {
    match value {
        Some(v) if v.is_finite() => format!("{v:.decimals$}"),
        _ => "—".to_string(),
    }
}
