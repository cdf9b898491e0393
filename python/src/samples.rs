//! A session as the command line reads it, turned into Arrow record batches (one per device,
//! one column per field, the MCAP times first) and JSON text for the header, the run events
//! and what was lost; and a results document's tables as the fleet export builds them.

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::Arc;

use arrow_array::builder::{Float64Builder, ListBuilder};
use arrow_array::{
    ArrayRef, BooleanArray, Float64Array, RecordBatch, StringArray, UInt32Array, UInt64Array,
};
use geocal::session::messages::{
    EnvSample, MachineStateSample, ProbeSample, RotaryStateSample, TracerSample,
};
use geocal::session::reader::{Completeness, Session, Stamped};

/// A record batch's columns by name.
type Columns = Vec<(&'static str, ArrayRef)>;

/// The session's parts, ready for Python.
pub struct SessionRead {
    pub header_json: String,
    pub events_json: String,
    pub losses_json: String,
    /// `tracers`, `env`, `rotary`, `machines`, `probes`, `topics` -> device id (or topic) ->
    /// its samples.
    pub devices: Vec<(&'static str, Vec<(String, RecordBatch)>)>,
}

pub fn read(path: &Path) -> anyhow::Result<SessionRead> {
    let session = geocal::session::reader::read_session(path)?;
    let events: Vec<serde_json::Value> = session
        .events
        .iter()
        .map(|e| {
            serde_json::json!({
                "log_time_ns": e.log_time_ns,
                "publish_time_ns": e.publish_time_ns,
                "event": e.msg,
            })
        })
        .collect();
    Ok(SessionRead {
        header_json: serde_json::to_string(&session.header)?,
        events_json: serde_json::to_string(&events)?,
        losses_json: serde_json::to_string(&losses(&session))?,
        devices: vec![
            ("tracers", batches(&session.tracers, tracer)?),
            ("env", batches(&session.env, env)?),
            ("rotary", batches(&session.rotary, rotary)?),
            ("machines", batches(&session.machines, machine)?),
            ("probes", batches(&session.probes, probe)?),
            ("topics", batches(&session.topics, topic)?),
        ],
    })
}

/// What the reader could not read, as `geocal solve` and `geocal repair` report it.
fn losses(session: &Session) -> serde_json::Value {
    let completeness = match &session.completeness {
        Completeness::Complete => serde_json::json!({"complete": true}),
        Completeness::Truncated {
            bytes_read,
            file_bytes,
            messages_read,
            reason,
        } => serde_json::json!({
            "complete": false,
            "bytes_read": bytes_read,
            "file_bytes": file_bytes,
            "messages_read": messages_read,
            "reason": reason,
        }),
    };
    serde_json::json!({
        "completeness": completeness,
        "damaged": session.damaged,
        "lost_before_repair": session.lost_before_repair,
        "skipped": session.skipped,
        "ignored": session.ignored,
    })
}

fn batches<T>(
    by_id: &BTreeMap<String, Vec<Stamped<T>>>,
    columns: fn(&[Stamped<T>]) -> Columns,
) -> anyhow::Result<Vec<(String, RecordBatch)>> {
    by_id
        .iter()
        .map(|(id, samples)| {
            let mut all: Columns = vec![
                (
                    "log_time_ns",
                    Arc::new(UInt64Array::from_iter_values(
                        samples.iter().map(|s| s.log_time_ns),
                    )),
                ),
                (
                    "publish_time_ns",
                    Arc::new(UInt64Array::from_iter_values(
                        samples.iter().map(|s| s.publish_time_ns),
                    )),
                ),
            ];
            all.extend(columns(samples));
            Ok((id.clone(), RecordBatch::try_from_iter(all)?))
        })
        .collect()
}

fn f64s<T>(samples: &[Stamped<T>], field: impl Fn(&T) -> f64) -> ArrayRef {
    Arc::new(Float64Array::from_iter_values(
        samples.iter().map(|s| field(&s.msg)),
    ))
}

fn optional_f64s<T>(samples: &[Stamped<T>], field: impl Fn(&T) -> Option<f64>) -> ArrayRef {
    Arc::new(
        samples
            .iter()
            .map(|s| field(&s.msg))
            .collect::<Float64Array>(),
    )
}

fn u64s<T>(samples: &[Stamped<T>], field: impl Fn(&T) -> u64) -> ArrayRef {
    Arc::new(UInt64Array::from_iter_values(
        samples.iter().map(|s| field(&s.msg)),
    ))
}

fn bools<T>(samples: &[Stamped<T>], field: impl Fn(&T) -> bool) -> ArrayRef {
    Arc::new(
        samples
            .iter()
            .map(|s| Some(field(&s.msg)))
            .collect::<BooleanArray>(),
    )
}

fn strings<T>(samples: &[Stamped<T>], field: impl Fn(&T) -> &str) -> ArrayRef {
    Arc::new(
        samples
            .iter()
            .map(|s| Some(field(&s.msg)))
            .collect::<StringArray>(),
    )
}

fn tracer(s: &[Stamped<TracerSample>]) -> Columns {
    vec![
        ("seq", u64s(s, |m| m.seq)),
        ("t_s", f64s(s, |m| m.t_s)),
        ("length_m", f64s(s, |m| m.length_m)),
        ("signal", f64s(s, |m| m.signal)),
        ("tracking", bools(s, |m| m.tracking)),
        (
            "beam_segment",
            Arc::new(UInt32Array::from_iter_values(
                s.iter().map(|m| m.msg.beam_segment),
            )),
        ),
    ]
}

fn env(s: &[Stamped<EnvSample>]) -> Columns {
    let mut material = ListBuilder::new(Float64Builder::new());
    for sample in s {
        material.values().append_slice(&sample.msg.material_temp_k);
        material.append(true);
    }
    vec![
        ("t_s", f64s(s, |m| m.t_s)),
        ("air_temp_k", f64s(s, |m| m.air_temp_k)),
        ("pressure_pa", f64s(s, |m| m.pressure_pa)),
        ("humidity_pct", f64s(s, |m| m.humidity_pct)),
        ("material_temp_k", Arc::new(material.finish())),
    ]
}

fn rotary(s: &[Stamped<RotaryStateSample>]) -> Columns {
    vec![
        ("t_s", f64s(s, |m| m.t_s)),
        ("commanded_rad", f64s(s, |m| m.commanded_rad)),
        ("encoder_rad", optional_f64s(s, |m| m.encoder_rad)),
        ("in_position", bools(s, |m| m.in_position)),
    ]
}

fn machine(s: &[Stamped<MachineStateSample>]) -> Columns {
    vec![
        ("t_s", f64s(s, |m| m.t_s)),
        ("state", strings(s, |m| &m.state)),
        ("x_m", f64s(s, |m| m.position_m[0])),
        ("y_m", f64s(s, |m| m.position_m[1])),
        ("z_m", f64s(s, |m| m.position_m[2])),
        ("frame", strings(s, |m| &m.frame)),
        ("feed_m_s", optional_f64s(s, |m| m.feed_m_s)),
    ]
}

fn probe(s: &[Stamped<ProbeSample>]) -> Columns {
    vec![
        ("seq", u64s(s, |m| m.seq)),
        ("t_s", f64s(s, |m| m.t_s)),
        ("value_m", optional_f64s(s, |m| m.value_m)),
    ]
}

/// A plan kind's own topic: each message's JSON text (the kind's method parses it).
fn topic(s: &[Stamped<serde_json::Value>]) -> Columns {
    let texts: Vec<String> = s.iter().map(|m| m.msg.to_string()).collect();
    vec![("json", Arc::new(StringArray::from(texts)))]
}

/// The parameters (with σ), points and error functions of a results document, as the fleet
/// export's tables (docs/fleet.md) without its run columns.
pub fn results_tables(
    results: &serde_json::Value,
) -> anyhow::Result<Vec<(&'static str, RecordBatch)>> {
    use geocal::export::{rows, schema, table};
    // The export's run columns are not null; they are dropped below.
    let run: table::RunCells = vec![
        ("run_id", "".into()),
        ("session_id", "".into()),
        ("kind", "".into()),
        ("started_at", table::Cell::TimeNs(0)),
    ];
    let own = |t: table::Table| -> anyhow::Result<RecordBatch> {
        let batch = t.to_batch()?;
        let keep: Vec<usize> = batch
            .schema()
            .fields()
            .iter()
            .enumerate()
            .filter(|(_, f)| !schema::RUN_COLUMNS.iter().any(|c| c.name == f.name()))
            .map(|(i, _)| i)
            .collect();
        Ok(batch.project(&keep)?)
    };
    Ok(vec![
        ("parameters", own(rows::parameters(results, &run))?),
        ("points", own(rows::points(results, &run))?),
        (
            "error_functions",
            own(rows::error_functions(results, &run))?,
        ),
    ])
}
