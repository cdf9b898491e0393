//! The multilateration report: the tracer network (method::report).

use crate::method::multilateration::MultilaterationResults;
use crate::method::report::multilateration_text;
use crate::method::KindResults;

impl KindResults for MultilaterationResults {
    fn report(&self) -> String {
        multilateration_text(self)
    }

    fn tracer_network(&self) -> Option<&MultilaterationResults> {
        Some(self)
    }
}
