//! What the console and the Modbus server ask of the controller: [`Machine`], taken as a
//! trait object (`&mut dyn Machine`).
//!
//! Every [`Controller<B>`] is one. The console's commands and reports and the Modbus
//! request handling are written against `dyn Machine`, not `Controller<B>`, so that they
//! are not generic over the board: compiled once, in this crate and at its opt-level
//! (the release profile builds this crate for size, `Cargo.toml`), instead of being
//! instantiated in the image's crate with the control step's opt-level (issue 20: they
//! are most of the code that is neither the control step nor start-up). A call through
//! the trait costs an indirect call; none of them is on the control step's path (the
//! board runs the console and Modbus jobs in the service's window, `src/board/owner.rs`).
//!
//! The methods are [`Controller`]'s own, of the same names; see there for each.

use crate::controller::{
    Bsp, CalibrateError, Controller, ControllerConfig, FaultRecord, HistoryEntry, MaintError,
    Refusal, Source, Status,
};
use crate::diag::{Crash, ResetCause, ResetCounts};
use crate::estimate::Estimate;
use crate::hx711::Calibration;
use crate::material::Material;
use crate::odometer::{Journal, Measurement, Odometer, WearLevel};
use crate::sequencer::{Request, State};
use crate::signature::monitor::HistoryCols;
use crate::signature::view::{CurveView, SignatureStatus, Which};
use crate::update::ImageReport;

/// The controller as its clients (console, Modbus) see it. See the module doc.
pub trait Machine {
    /// [`Controller::state`].
    fn state(&self) -> State;
    /// [`Controller::status`].
    fn status(&self) -> Status;
    /// [`Controller::is_quiet`].
    fn is_quiet(&self) -> bool;
    /// [`Controller::calibrated`].
    fn calibrated(&self) -> bool;
    /// [`Controller::config`].
    fn config(&self) -> &ControllerConfig;
    /// [`Controller::odometer`].
    fn odometer(&self) -> &Odometer;
    /// [`Controller::journal`].
    fn journal(&self) -> Journal;
    /// [`Controller::measurements`].
    fn measurements(&self) -> &[Measurement];
    /// [`Controller::baseline_or_nominal`].
    fn baseline_or_nominal(&self) -> u32;
    /// [`Controller::wear_estimate`].
    fn wear_estimate(&self) -> Estimate;
    /// [`Controller::wear_level`].
    fn wear_level(&self) -> WearLevel;
    /// [`Controller::history`], each entry to `out`.
    fn history(&mut self, max: usize, out: &mut dyn FnMut(HistoryEntry)) -> usize;
    /// [`Controller::faults`], each record to `out`, oldest first.
    fn each_fault(&self, out: &mut dyn FnMut(&FaultRecord));
    /// [`Controller::fault_count`].
    fn fault_count(&self) -> u32;
    /// [`Controller::overload_trips`].
    fn overload_trips(&self) -> u32;
    /// [`Controller::reset_counts`].
    fn reset_counts(&self) -> ResetCounts;
    /// [`Controller::last_reset`].
    fn last_reset(&self) -> Option<ResetCause>;
    /// [`Controller::last_crash`].
    fn last_crash(&self) -> Option<Crash>;
    /// [`Controller::stack_usage`].
    fn stack_usage(&self) -> Option<(u32, u32)>;
    /// [`Controller::records_queued`].
    fn records_queued(&self) -> usize;
    /// [`Controller::records_dropped`].
    fn records_dropped(&self) -> u32;
    /// [`Controller::maintenance_mode`].
    fn maintenance_mode(&self) -> bool;
    /// [`Controller::set_maintenance_mode`].
    fn set_maintenance_mode(&mut self, on: bool);
    /// [`Controller::command`].
    fn command(&mut self, r: Request) -> Result<(), Refusal>;
    /// [`Controller::command_from`].
    fn command_from(&mut self, source: Source, r: Request) -> Result<(), Refusal>;
    /// [`Controller::store_rate`].
    fn store_rate(&mut self, rate_sps: u32) -> Result<(), MaintError>;
    /// [`Controller::bor_level`].
    fn bor_level(&self) -> u8;
    /// [`Controller::program_bor`].
    fn program_bor(&mut self) -> Result<u8, MaintError>;
    /// [`Controller::load_record`].
    fn load_record(&mut self, kind: u8, buf: &mut [u8]) -> Option<usize>;
    /// [`Controller::store_record`].
    fn store_record(&mut self, kind: u8, data: &[u8]) -> Result<(), MaintError>;
    /// [`Controller::write_or_queue_record`].
    fn write_or_queue_record(&mut self, kind: u8, data: &[u8]) -> bool;
    /// [`Controller::replace_cone_measured`].
    fn replace_cone_measured(
        &mut self,
        material: Material,
        serial: &str,
        baseline_um: Option<u32>,
    ) -> Result<(), MaintError>;
    /// [`Controller::add_measurement`].
    fn add_measurement(&mut self, bore_um: u32, baseline: bool) -> Result<Measurement, MaintError>;
    /// [`Controller::calibrate_tare`].
    fn calibrate_tare(&mut self) -> Result<Calibration, CalibrateError>;
    /// [`Controller::calibrate_span`].
    fn calibrate_span(&mut self, force_mn: i32) -> Result<Calibration, CalibrateError>;
    /// [`Controller::images`].
    fn images(&self) -> ImageReport;
    /// [`Controller::set_images`].
    fn set_images(&mut self, images: ImageReport);
    /// [`Controller::begin_update`].
    fn begin_update(&mut self) -> Result<(), MaintError>;
    /// [`Controller::end_update`].
    fn end_update(&mut self);
    /// [`Controller::signature_status`].
    fn signature_status(&self) -> SignatureStatus;
    /// [`Controller::curve`].
    fn curve(&mut self, which: Which, out: &mut CurveView) -> bool;
    /// [`Controller::signature_history`].
    fn signature_history(&self, cycle: u32) -> Option<HistoryCols>;
}

impl<B: Bsp> Machine for Controller<B> {
    fn state(&self) -> State {
        Controller::state(self)
    }
    fn status(&self) -> Status {
        Controller::status(self)
    }
    fn is_quiet(&self) -> bool {
        Controller::is_quiet(self)
    }
    fn calibrated(&self) -> bool {
        Controller::calibrated(self)
    }
    fn config(&self) -> &ControllerConfig {
        Controller::config(self)
    }
    fn odometer(&self) -> &Odometer {
        Controller::odometer(self)
    }
    fn journal(&self) -> Journal {
        Controller::journal(self)
    }
    fn measurements(&self) -> &[Measurement] {
        Controller::measurements(self)
    }
    fn baseline_or_nominal(&self) -> u32 {
        Controller::baseline_or_nominal(self)
    }
    fn wear_estimate(&self) -> Estimate {
        Controller::wear_estimate(self)
    }
    fn wear_level(&self) -> WearLevel {
        Controller::wear_level(self)
    }
    fn history(&mut self, max: usize, out: &mut dyn FnMut(HistoryEntry)) -> usize {
        Controller::history(self, max, out)
    }
    fn each_fault(&self, out: &mut dyn FnMut(&FaultRecord)) {
        Controller::faults(self).for_each(out)
    }
    fn fault_count(&self) -> u32 {
        Controller::fault_count(self)
    }
    fn overload_trips(&self) -> u32 {
        Controller::overload_trips(self)
    }
    fn reset_counts(&self) -> ResetCounts {
        Controller::reset_counts(self)
    }
    fn last_reset(&self) -> Option<ResetCause> {
        Controller::last_reset(self)
    }
    fn last_crash(&self) -> Option<Crash> {
        Controller::last_crash(self)
    }
    fn stack_usage(&self) -> Option<(u32, u32)> {
        Controller::stack_usage(self)
    }
    fn records_queued(&self) -> usize {
        Controller::records_queued(self)
    }
    fn records_dropped(&self) -> u32 {
        Controller::records_dropped(self)
    }
    fn maintenance_mode(&self) -> bool {
        Controller::maintenance_mode(self)
    }
    fn set_maintenance_mode(&mut self, on: bool) {
        Controller::set_maintenance_mode(self, on)
    }
    fn command(&mut self, r: Request) -> Result<(), Refusal> {
        Controller::command(self, r)
    }
    fn command_from(&mut self, source: Source, r: Request) -> Result<(), Refusal> {
        Controller::command_from(self, source, r)
    }
    fn store_rate(&mut self, rate_sps: u32) -> Result<(), MaintError> {
        Controller::store_rate(self, rate_sps)
    }
    fn bor_level(&self) -> u8 {
        Controller::bor_level(self)
    }
    fn program_bor(&mut self) -> Result<u8, MaintError> {
        Controller::program_bor(self)
    }
    fn load_record(&mut self, kind: u8, buf: &mut [u8]) -> Option<usize> {
        Controller::load_record(self, kind, buf)
    }
    fn store_record(&mut self, kind: u8, data: &[u8]) -> Result<(), MaintError> {
        Controller::store_record(self, kind, data)
    }
    fn write_or_queue_record(&mut self, kind: u8, data: &[u8]) -> bool {
        Controller::write_or_queue_record(self, kind, data)
    }
    fn replace_cone_measured(
        &mut self,
        material: Material,
        serial: &str,
        baseline_um: Option<u32>,
    ) -> Result<(), MaintError> {
        Controller::replace_cone_measured(self, material, serial, baseline_um)
    }
    fn add_measurement(&mut self, bore_um: u32, baseline: bool) -> Result<Measurement, MaintError> {
        Controller::add_measurement(self, bore_um, baseline)
    }
    fn calibrate_tare(&mut self) -> Result<Calibration, CalibrateError> {
        Controller::calibrate_tare(self)
    }
    fn calibrate_span(&mut self, force_mn: i32) -> Result<Calibration, CalibrateError> {
        Controller::calibrate_span(self, force_mn)
    }
    fn images(&self) -> ImageReport {
        Controller::images(self)
    }
    fn set_images(&mut self, images: ImageReport) {
        Controller::set_images(self, images)
    }
    fn begin_update(&mut self) -> Result<(), MaintError> {
        Controller::begin_update(self)
    }
    fn end_update(&mut self) {
        Controller::end_update(self)
    }
    fn signature_status(&self) -> SignatureStatus {
        Controller::signature_status(self)
    }
    fn curve(&mut self, which: Which, out: &mut CurveView) -> bool {
        Controller::curve(self, which, out)
    }
    fn signature_history(&self, cycle: u32) -> Option<HistoryCols> {
        Controller::signature_history(self, cycle)
    }
}
