//! The board description and the world outside the MCU.
//!
//! [`WIRING`] is data: which pin of which port carries which signal, and what the board
//! puts on the line when nothing drives it (its external pull). The models are
//! hil-sim's ([`hil_sim::rig::Machine`]): the same axis, lock, load cell and dock-request
//! line the host rig uses, here driven by and read from the pins of the emulated MCU. The
//! odometer's flash sectors are hil-sim's [`SharedFlash`] (NOR semantics, erase counters,
//! power-cut injection).

use embedded_hal::digital::{InputPin, OutputPin};
use hil_sim::axis::AxisPin;
use hil_sim::flash::SharedFlash;
use hil_sim::hx711::{Hx711Dout, Hx711Fault, Hx711Sck};
use hil_sim::lock::LockPin;
use hil_sim::rig::{Machine, ProfileForce};

/// A signal of the board.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Signal {
    /// Propulsion driver STEP (MCU → driver).
    Step,
    /// Propulsion driver DIR.
    Dir,
    /// Propulsion driver EN, active low.
    EnN,
    /// Lock H-bridge IN1 (toward locked).
    LockIn1,
    /// Lock H-bridge IN2 (toward released).
    LockIn2,
    /// Home switch (to ground when closed).
    Home,
    /// End switch.
    End,
    /// Lock-locked switch.
    Locked,
    /// Lock-released switch.
    Released,
    /// HX711 DOUT (HX711 → MCU).
    HxDout,
    /// HX711 PD_SCK (MCU → HX711).
    HxSck,
    /// The PLC's DOCK (level, active low: asserted = "be docked").
    Dock,
    /// The PLC's E-STOP (normally closed to ground: open = high = stop).
    Estop,
    /// READY to the PLC (active high).
    Ready,
    /// MATED to the PLC.
    Mated,
    /// FAULT to the PLC.
    Fault,
    /// MAINTENANCE to the PLC.
    Maintenance,
    /// Console USART2 TX (alternate function 7).
    ConsoleTx,
    /// Modbus USART3 TX (alternate function 7) to the RS-485 transceiver.
    ModbusTx,
    /// Modbus USART3 RX (alternate function 7).
    ModbusRx,
    /// The RS-485 transceiver's driver enable (high: we drive the bus).
    ModbusDe,
    /// Console USART2 RX (alternate function 7).
    ConsoleRx,
}

impl Signal {
    /// Whether the MCU drives it (an output of the board's MCU).
    pub fn is_output(self) -> bool {
        matches!(
            self,
            Self::Step
                | Self::Dir
                | Self::EnN
                | Self::LockIn1
                | Self::LockIn2
                | Self::HxSck
                | Self::Ready
                | Self::Mated
                | Self::Fault
                | Self::Maintenance
                | Self::ModbusDe
        )
    }
}

/// What the board puts on a line nobody drives.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Ext {
    /// Nothing: the line floats (the MCU must pull it).
    Float,
    /// An external pull-up.
    Up,
    /// An external pull-down.
    Down,
}

/// One wire: port (0 = A), pin, signal, external pull.
#[derive(Clone, Copy, Debug)]
pub struct Wire {
    /// Port, 0 = A.
    pub port: u8,
    /// Pin number.
    pub pin: u8,
    /// Signal.
    pub signal: Signal,
    /// External pull.
    pub ext: Ext,
}

const A: u8 = 0;
const B: u8 = 1;
const C: u8 = 2;
const D: u8 = 3;
const E: u8 = 4;

/// The controller board (the pin map in docs/board.md). The driver and bridge inputs have external
/// pulls to their safe level, so a floating MCU pin (during and after reset) is a
/// disabled motor: EN pulled up (driver off), STEP and both bridge inputs pulled down.
pub const WIRING: &[Wire] = &[
    Wire {
        port: E,
        pin: 9,
        signal: Signal::Step,
        ext: Ext::Down,
    },
    Wire {
        port: E,
        pin: 10,
        signal: Signal::Dir,
        ext: Ext::Down,
    },
    Wire {
        port: E,
        pin: 11,
        signal: Signal::EnN,
        ext: Ext::Up,
    },
    Wire {
        port: D,
        pin: 12,
        signal: Signal::LockIn1,
        ext: Ext::Down,
    },
    Wire {
        port: D,
        pin: 13,
        signal: Signal::LockIn2,
        ext: Ext::Down,
    },
    Wire {
        port: C,
        pin: 0,
        signal: Signal::Home,
        ext: Ext::Float,
    },
    Wire {
        port: C,
        pin: 1,
        signal: Signal::End,
        ext: Ext::Float,
    },
    Wire {
        port: C,
        pin: 2,
        signal: Signal::Locked,
        ext: Ext::Float,
    },
    Wire {
        port: C,
        pin: 3,
        signal: Signal::Released,
        ext: Ext::Float,
    },
    Wire {
        port: B,
        pin: 0,
        signal: Signal::HxDout,
        ext: Ext::Float,
    },
    Wire {
        port: B,
        pin: 1,
        signal: Signal::HxSck,
        ext: Ext::Down,
    },
    Wire {
        port: C,
        pin: 4,
        signal: Signal::Dock,
        ext: Ext::Float,
    },
    Wire {
        port: C,
        pin: 5,
        signal: Signal::Estop,
        ext: Ext::Float,
    },
    Wire {
        port: D,
        pin: 0,
        signal: Signal::Ready,
        ext: Ext::Down,
    },
    Wire {
        port: D,
        pin: 1,
        signal: Signal::Mated,
        ext: Ext::Down,
    },
    Wire {
        port: D,
        pin: 2,
        signal: Signal::Fault,
        ext: Ext::Down,
    },
    Wire {
        port: D,
        pin: 3,
        signal: Signal::Maintenance,
        ext: Ext::Down,
    },
    Wire {
        port: B,
        pin: 10,
        signal: Signal::ModbusTx,
        ext: Ext::Float,
    },
    Wire {
        port: B,
        pin: 11,
        signal: Signal::ModbusRx,
        ext: Ext::Float,
    },
    Wire {
        port: B,
        pin: 14,
        signal: Signal::ModbusDe,
        ext: Ext::Down,
    },
    Wire {
        port: A,
        pin: 2,
        signal: Signal::ConsoleTx,
        ext: Ext::Float,
    },
    Wire {
        port: A,
        pin: 3,
        signal: Signal::ConsoleRx,
        ext: Ext::Float,
    },
];

/// The wire on `port`/`pin`, if any.
pub fn wire_at(port: u8, pin: u8) -> Option<&'static Wire> {
    // A table by port and pin (ports A–I), built at compile time: read at every EXTI
    // sample and pin read.
    const PORTS: usize = 9;
    const _: () = assert!(WIRING.len() < u8::MAX as usize);
    const AT: [[u8; 16]; PORTS] = {
        let mut at = [[u8::MAX; 16]; PORTS];
        let mut i = 0;
        while i < WIRING.len() {
            let w = &WIRING[i];
            if (w.port as usize) < PORTS
                && w.pin < 16
                && at[w.port as usize][w.pin as usize] == u8::MAX
            {
                at[w.port as usize][w.pin as usize] = i as u8;
            }
            i += 1;
        }
        at
    };
    let i = *AT.get(port as usize)?.get(pin as usize)?;
    WIRING.get(i as usize)
}

/// The wire of `signal`.
pub fn wire_of(signal: Signal) -> Option<&'static Wire> {
    WIRING.iter().find(|w| w.signal == signal)
}

/// The machine outside the MCU.
pub struct World {
    /// hil-sim's devices on their shared clock.
    pub machine: Machine,
    /// The odometer sectors (10 and 11).
    pub flash: SharedFlash,
    step: AxisPin,
    dir: AxisPin,
    en_n: AxisPin,
    home: AxisPin,
    end: AxisPin,
    in1: LockPin,
    in2: LockPin,
    locked: LockPin,
    released: LockPin,
    dout: Hx711Dout<ProfileForce>,
    sck: Hx711Sck<ProfileForce>,
    /// What the PLC reads: READY, MATED, FAULT, MAINTENANCE.
    pub plc_out: PlcOutputs,
}

/// The handshake outputs as the PLC sees them (the pins' levels).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct PlcOutputs {
    /// READY.
    pub ready: bool,
    /// MATED.
    pub mated: bool,
    /// FAULT.
    pub fault: bool,
    /// MAINTENANCE.
    pub maintenance: bool,
}

impl World {
    /// Wire `machine` and the odometer `flash`.
    pub fn new(machine: Machine, flash: SharedFlash) -> Self {
        let (axis, lock, hx) = (&machine.axis, &machine.lock, &machine.hx);
        Self {
            step: axis.step(),
            dir: axis.dir(),
            en_n: axis.enable_n(),
            home: axis.home_switch(),
            end: axis.end_switch(),
            in1: lock.in1(),
            in2: lock.in2(),
            locked: lock.locked_switch(),
            released: lock.released_switch(),
            dout: hx.dout(),
            sck: hx.pd_sck(),
            plc_out: PlcOutputs::default(),
            machine,
            flash,
        }
    }

    fn at(&self, t_ns: u64) {
        self.machine.clock.advance_to_ns(t_ns);
    }

    /// The MCU's line `signal` is at `high` from `t_ns` on (an input of a device).
    pub fn drive(&mut self, signal: Signal, high: bool, t_ns: u64) {
        self.at(t_ns);
        let pin: &mut dyn OutputPinDyn = match signal {
            Signal::Step => &mut self.step,
            Signal::Dir => &mut self.dir,
            Signal::EnN => &mut self.en_n,
            Signal::LockIn1 => &mut self.in1,
            Signal::LockIn2 => &mut self.in2,
            Signal::HxSck => &mut self.sck,
            Signal::Ready => {
                self.plc_out.ready = high;
                return;
            }
            Signal::Mated => {
                self.plc_out.mated = high;
                return;
            }
            Signal::Fault => {
                self.plc_out.fault = high;
                return;
            }
            Signal::Maintenance => {
                self.plc_out.maintenance = high;
                return;
            }
            _ => return,
        };
        pin.set(high);
    }

    /// What a device puts on line `signal` at `t_ns`: `Some(level)` when it drives it,
    /// `None` when it leaves it open (an open switch contact, a disconnected sensor).
    pub fn sense(&mut self, signal: Signal, t_ns: u64) -> Option<bool> {
        self.at(t_ns);
        // Switches close to ground (active low); open, they leave the line to the pulls.
        let closed = |p: &mut dyn InputPinDyn| p.low().then_some(false);
        match signal {
            Signal::Home => closed(&mut self.home),
            Signal::End => closed(&mut self.end),
            Signal::Locked => closed(&mut self.locked),
            Signal::Released => closed(&mut self.released),
            Signal::HxDout => {
                if self.machine.hx.fault() == Hx711Fault::Disconnected {
                    None
                } else {
                    Some(!self.dout.low())
                }
            }
            // A PLC output (a transistor to ground when asserted).
            Signal::Dock => (!self.machine.dock_request.is_high()).then_some(false),
            // A normally-closed contact to ground: open leaves the line to the pull-up.
            Signal::Estop => (!self.machine.estop.is_high()).then_some(false),
            _ => None,
        }
    }

    /// The next time a device changes a line by itself (an HX711 conversion: DOUT
    /// falls), ns.
    pub fn next_change_ns(&self) -> u64 {
        self.machine.hx.next_conversion_ns()
    }
}

/// Object-safe pin setters over hil-sim's pin types (all infallible).
trait OutputPinDyn {
    fn set(&mut self, high: bool);
}

impl<P: OutputPin<Error = core::convert::Infallible>> OutputPinDyn for P {
    fn set(&mut self, high: bool) {
        let _ = if high {
            self.set_high()
        } else {
            self.set_low()
        };
    }
}

trait InputPinDyn {
    fn low(&mut self) -> bool;
}

impl<P: InputPin<Error = core::convert::Infallible>> InputPinDyn for P {
    fn low(&mut self) -> bool {
        self.is_low().unwrap_or(false)
    }
}
