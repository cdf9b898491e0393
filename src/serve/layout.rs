//! Where a run's stations go, for the operator: the machine's travel and the plan's station
//! hints, read from the plan configuration the job stored (`plan.toml`).

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

/// The travel of one machine axis, metres.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct AxisTravel {
    pub axis: String,
    pub from_m: f64,
    pub to_m: f64,
}

/// A tracer station of the plan and where it is roughly expected (machine frame, metres).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct StationHint {
    pub id: String,
    pub hint_m: Option<[f64; 3]>,
}

/// A run's station layout; empty for plans without stations (or without a stored plan).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct StationLayout {
    /// `[machine] travel_m`, by axis name.
    pub travel: Vec<AxisTravel>,
    /// `[[plan.stations]]`, in the plan's order.
    pub stations: Vec<StationHint>,
}

/// The layout a plan configuration declares; keys it lacks or that do not parse are left out.
pub fn of_plan(text: &str) -> StationLayout {
    let Ok(plan) = text.parse::<toml::Table>() else {
        return StationLayout::default();
    };
    let number = |v: &toml::Value| v.as_float().or_else(|| v.as_integer().map(|i| i as f64));
    let travel = plan
        .get("machine")
        .and_then(|m| m.get("travel_m"))
        .and_then(|t| t.as_table())
        .map(|axes| {
            axes.iter()
                .filter_map(|(axis, range)| {
                    let range = range.as_array()?;
                    match range.as_slice() {
                        [from, to] => Some(AxisTravel {
                            axis: axis.clone(),
                            from_m: number(from)?,
                            to_m: number(to)?,
                        }),
                        _ => None,
                    }
                })
                .collect()
        })
        .unwrap_or_default();
    let stations = plan
        .get("plan")
        .and_then(|p| p.get("stations"))
        .and_then(|s| s.as_array())
        .map(|stations| {
            stations
                .iter()
                .filter_map(|station| {
                    let id = station.get("id")?.as_str()?.to_owned();
                    let hint_m = station
                        .get("hint_m")
                        .and_then(|h| h.as_array())
                        .and_then(|h| match h.as_slice() {
                            [x, y, z] => Some([number(x)?, number(y)?, number(z)?]),
                            _ => None,
                        });
                    Some(StationHint { id, hint_m })
                })
                .collect()
        })
        .unwrap_or_default();
    StationLayout { travel, stations }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_demo_declares_its_travel_and_five_station_hints() {
        let layout = of_plan(include_str!("../../config/demo-multilateration.toml"));
        let axes: Vec<(&str, f64, f64)> = layout
            .travel
            .iter()
            .map(|a| (a.axis.as_str(), a.from_m, a.to_m))
            .collect();
        assert_eq!(axes, [("x", 0.0, 1.4), ("y", 0.0, 2.4), ("z", 0.0, 1.0)]);
        assert_eq!(layout.stations.len(), 5);
        assert_eq!(layout.stations[1].id, "s2");
        assert_eq!(layout.stations[1].hint_m, Some([1.55, 0.05, -0.15]));
        assert_eq!(of_plan("not toml ["), StationLayout::default());
    }
}
