//! A digital line driven from outside the controller: a push-button, a PLC output, a
//! relay contact. The board reads it as an input pin; a scene (or a test) sets its level.

use std::cell::Cell;
use std::rc::Rc;

/// A shared line level (`true` = high). Clones share the level.
#[derive(Clone, Debug)]
pub struct SimLine(Rc<Cell<bool>>);

impl SimLine {
    /// A line resting at `high`.
    pub fn new(high: bool) -> Self {
        Self(Rc::new(Cell::new(high)))
    }

    /// Drive the line.
    pub fn set(&self, high: bool) {
        self.0.set(high);
    }

    /// The line's level now.
    pub fn is_high(&self) -> bool {
        self.0.get()
    }
}

impl embedded_hal::digital::ErrorType for SimLine {
    type Error = core::convert::Infallible;
}

impl embedded_hal::digital::InputPin for SimLine {
    fn is_high(&mut self) -> Result<bool, Self::Error> {
        Ok(self.0.get())
    }
    fn is_low(&mut self) -> Result<bool, Self::Error> {
        Ok(!self.0.get())
    }
}
