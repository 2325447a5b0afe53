//! # Modbus RTU server for the vehicle's PLC
//!
//! The PLC reads the controller's status, counters and cone record, and commands dock,
//! undock, clear fault, stop and home, over RS-485 in Modbus RTU. This module is the
//! server side: a byte-at-a-time frame receiver ([`RtuFramer`]), the register map, and a
//! [`Server`] that turns a request frame into a reply frame. It is `no_std`, allocates
//! nothing, and never panics on input (every frame, any bytes, gets a reply or nothing).
//!
//! ## Serial line
//!
//! 8 data bits, even parity, 1 stop bit (**8E1**, fixed: 11 bits a character), at one of
//! 9600, 19 200 (default), 38 400, 57 600 or 115 200 baud; unit address 1–247 (default
//! 1). The board layer owns the UART; it timestamps every received byte (µs, at the end
//! of its stop bit — the receive interrupt) and hands it to [`Server::on_byte`], reports
//! a character with a parity, framing or overrun error to [`Server::on_line_error`], and
//! calls [`Server::poll`] often (every pass of its loop): a reply, if any, is returned
//! once the request has ended and is to be sent as it is (CRC included), with the
//! transceiver's driver enabled for exactly its bytes.
//!
//! ## By hand
//!
//! The CRC over the whole frame, each function's frame length, the quantity and
//! byte-count limits, the function codes, device identification (0x2B) and the replies
//! are all done here (`pdu.rs`). The replies of functions 0x01–0x06, 0x0F and 0x10 were
//! built by the `rmodbus` crate up to issue 20, after these same checks (it answers an
//! unknown function before checking the CRC, checks the CRC only over the length it
//! expects, accepts a quantity of 0, does not match the byte count of 0x0F/0x10 to the
//! quantity, computes `7 + byte count` and `function + 0x80` in a `u8`, and lacks 0x2B);
//! what remained its part, a read's header and a write's echo, cost 1 960 B of flash,
//! and is the same bytes by hand (host-tests/tests/modbus_transcript.rs).
//!
//! The parts, one file each: [`settings`] (unit address and baud rate in flash),
//! [`framer`] (RTU framing at character resolution), [`map`] (the register map),
//! [`ident`] (device identification), [`pdu`] (request handling), [`server`] (the three
//! together, with statistics).

pub mod framer;
pub mod ident;
pub mod map;
pub mod pdu;
pub mod server;
pub mod settings;

pub use framer::*;
pub use ident::*;
pub use map::*;
pub use pdu::*;
pub use server::*;
pub use settings::*;

/// Largest RTU frame (address, PDU, CRC), bytes.
pub const MAX_FRAME: usize = 256;
/// Shortest frame that can be a request (address, function, CRC), bytes.
pub const MIN_FRAME: usize = 4;
/// The broadcast address.
pub const BROADCAST: u8 = 0;
/// Bits a character on the line: start, 8 data, parity, stop (8E1).
pub const BITS_PER_CHAR: u32 = 11;
/// The baud rates a unit may be set to.
pub const BAUD_RATES: [u32; 5] = [9_600, 19_200, 38_400, 57_600, 115_200];

/// CRC-16/MODBUS of `bytes` (sent on the line low byte first).
pub fn crc16(bytes: &[u8]) -> u16 {
    crate::crc::crc16_modbus(bytes)
}

/// Exception codes.
pub mod exception {
    /// The function (or MEI type) is not supported, **or** the command is one the
    /// controller does not accept in its present state (the specification's "server in
    /// the wrong state"; the reason is in input register 9).
    pub const ILLEGAL_FUNCTION: u8 = 0x01;
    /// An address (range) outside the map, or not writable.
    pub const ILLEGAL_DATA_ADDRESS: u8 = 0x02;
    /// A quantity, byte count, length or value that is not allowed.
    pub const ILLEGAL_DATA_VALUE: u8 = 0x03;
}

#[cfg(test)]
mod tests {
    use super::map::{centimillimetres, decinewtons, parse_u16};
    use super::pdu::validate;
    use super::*;
    use crate::sequencer::State;

    /// docs/modbus-map.md is the map's one table (and map.rs's doc): its last input
    /// register and its map version are the code's.
    #[test]
    fn the_register_map_page_ends_where_the_map_does() {
        let page = include_str!("../../../../docs/modbus-map.md");
        // A row's cells as numbers (a cell that is not one: None).
        let row = |name: &str| -> heapless::Vec<Option<u16>, 8> {
            page.lines()
                .find(|l| l.starts_with("| ") && l.contains(name))
                .unwrap_or_else(|| panic!("no row {name}"))
                .split('|')
                .map(|c| c.trim().parse().ok())
                .collect()
        };
        let version = row("register map version");
        assert_eq!(version[3], Some(MAP_VERSION), "map version");
        // The input registers' table ends at the map's last register.
        let table_end = page
            .lines()
            .skip_while(|l| !l.starts_with("**Input registers**"))
            .skip_while(|l| !l.starts_with('|'))
            .take_while(|l| l.starts_with('|'))
            .last()
            .expect("the input register table");
        let last: Option<u16> = table_end
            .split('|')
            .nth(1)
            .and_then(|c| c.trim().rsplit(['–', '-']).next())
            .and_then(|c| c.trim().parse().ok());
        assert_eq!(last, Some(ir::COUNT - 1), "last input register");
        let last_coil = row("home, after a reset");
        assert_eq!(last_coil[1], Some(COIL_COUNT - 1), "last coil");
    }

    #[test]
    fn settings_validate_and_round_trip() {
        assert_eq!(ModbusSettings::default(), ModbusSettings::DEFAULT);
        assert!(ModbusSettings::DEFAULT.is_valid());
        for baud in BAUD_RATES {
            for unit in [1, 2, 100, 247] {
                let s = ModbusSettings::new(unit, baud).unwrap();
                assert_eq!(ModbusSettings::from_bytes(&s.to_bytes()), Some(s));
            }
        }
        assert_eq!(ModbusSettings::new(0, 19_200), None);
        assert_eq!(ModbusSettings::new(248, 19_200), None);
        assert_eq!(ModbusSettings::new(255, 19_200), None);
        for baud in [0, 1_200, 4_800, 14_400, 19_201, 230_400, u32::MAX] {
            assert_eq!(ModbusSettings::new(1, baud), None, "{baud}");
        }
        let b = ModbusSettings::DEFAULT.to_bytes();
        assert_eq!(b, [1, 0, 0x00, 0x4B, 0x00, 0x00]);
        // Wrong length, format, or a value out of range: refused.
        assert_eq!(ModbusSettings::from_bytes(&b[..5]), None);
        assert_eq!(ModbusSettings::from_bytes(&[1, 0, 0, 0x4B, 0, 0, 0]), None);
        assert_eq!(ModbusSettings::from_bytes(&[1, 1, 0, 0x4B, 0, 0]), None);
        assert_eq!(ModbusSettings::from_bytes(&[0, 0, 0, 0x4B, 0, 0]), None);
        assert_eq!(ModbusSettings::from_bytes(&[1, 0, 0, 0x4C, 0, 0]), None);
        assert_eq!(ModbusSettings::from_bytes(&[0xFF; 6]), None);
    }

    #[test]
    fn character_times_follow_the_serial_line_spec() {
        let t = |baud| {
            let s = ModbusSettings { unit: 1, baud };
            (s.char_us(), s.t1_5_us(), s.t3_5_us())
        };
        assert_eq!(t(9_600), (1_146, 1_719, 4_011));
        assert_eq!(t(19_200), (573, 860, 2_006));
        assert_eq!(t(38_400), (287, 750, 1_750));
        assert_eq!(t(57_600), (191, 750, 1_750));
        assert_eq!(t(115_200), (96, 750, 1_750));
        // No division by zero on nonsense.
        let _ = t(0);
    }

    #[test]
    fn crc_matches_the_spec_example() {
        // Modbus over serial line, §6.2.2 style example: 01 03 00 00 00 0A → C5 CD.
        assert_eq!(
            crc16(&[0x01, 0x03, 0x00, 0x00, 0x00, 0x0A]).to_le_bytes(),
            [0xC5, 0xCD]
        );
    }

    #[test]
    fn firmware_version_is_the_package_version() {
        let v = env!("CARGO_PKG_VERSION");
        let mut parts = v.split(['.', '-', '+']).map(|p| p.parse::<u16>().unwrap());
        assert_eq!(
            FIRMWARE_VERSION,
            [
                parts.next().unwrap(),
                parts.next().unwrap(),
                parts.next().unwrap()
            ]
        );
        assert_eq!(parse_u16("12rc"), 12);
        assert_eq!(parse_u16(""), 0);
        assert_eq!(parse_u16("99999999"), u16::MAX);
    }

    #[test]
    fn scaling_rounds_and_saturates() {
        assert_eq!(decinewtons(0), 0);
        assert_eq!(decinewtons(125_098), 1_251);
        assert_eq!(decinewtons(49), 0);
        assert_eq!(decinewtons(50), 1);
        assert_eq!(decinewtons(-50) as i16, -1);
        assert_eq!(decinewtons(-149) as i16, -1);
        assert_eq!(decinewtons(i32::MAX) as i16, i16::MAX);
        assert_eq!(decinewtons(i32::MIN) as i16, i16::MIN);
        assert_eq!(centimillimetres(50_004), 5_000);
        assert_eq!(centimillimetres(-3_000) as i16, -300);
        assert_eq!(centimillimetres(i32::MAX) as i16, i16::MAX);
    }

    #[test]
    fn commands_codes_and_coils_agree() {
        for (i, c) in Command::ALL.into_iter().enumerate() {
            assert_eq!(c.coil() as usize, i);
            assert_eq!(Command::from_code(c.code()), Some(c));
        }
        assert_eq!(Command::from_code(0), None);
        assert_eq!(Command::from_code(6), None);
        assert_eq!(COIL_COUNT as usize, Command::ALL.len());
        assert!(!Command::Stop.moves() && Command::Dock.moves());
    }

    #[test]
    fn validation_checks_length_quantity_and_byte_count() {
        let v = |pdu: &[u8]| validate(pdu[0], pdu);
        assert_eq!(v(&[0x04, 0, 0, 0, 1]), Ok(()));
        assert_eq!(v(&[0x04, 0, 0, 0, 125]), Ok(()));
        assert_eq!(v(&[0x04, 0, 0, 0, 126]), Err(3));
        assert_eq!(v(&[0x04, 0, 0, 0, 0]), Err(3));
        assert_eq!(v(&[0x04, 0, 0, 0]), Err(3));
        assert_eq!(v(&[0x04, 0, 0, 0, 1, 0]), Err(3));
        assert_eq!(v(&[0x01, 0, 0, 0x07, 0xD0]), Ok(()));
        assert_eq!(v(&[0x01, 0, 0, 0x07, 0xD1]), Err(3));
        assert_eq!(v(&[0x05, 0, 0, 0xFF, 0x00]), Ok(()));
        assert_eq!(v(&[0x05, 0, 0, 0x00, 0x00]), Ok(()));
        assert_eq!(v(&[0x05, 0, 0, 0x00, 0x01]), Err(3));
        assert_eq!(v(&[0x06, 0, 0, 0xAB, 0xCD]), Ok(()));
        assert_eq!(v(&[0x0F, 0, 0, 0, 9, 2, 0xFF, 0x01]), Ok(()));
        assert_eq!(v(&[0x0F, 0, 0, 0, 9, 1, 0xFF]), Err(3));
        assert_eq!(v(&[0x0F, 0, 0, 0, 9, 2, 0xFF]), Err(3));
        assert_eq!(v(&[0x0F, 0, 0, 0, 0, 0]), Err(3));
        assert_eq!(v(&[0x10, 0, 0, 0, 1, 2, 0, 1]), Ok(()));
        assert_eq!(v(&[0x10, 0, 0, 0, 1, 3, 0, 1, 0]), Err(3));
        assert_eq!(v(&[0x10, 0, 0, 0, 124, 248]), Err(3));
        assert_eq!(v(&[0x10, 0, 0, 0, 1, 255]), Err(3));
        assert_eq!(v(&[0x10, 0, 0]), Err(3));
        assert_eq!(v(&[0x07]), Err(1));
    }

    #[test]
    fn state_codes_are_distinct() {
        use crate::sequencer::{AfterLock, FaultKind};
        let states = [
            State::PowerUp,
            State::Homing { deadline_ms: 0 },
            State::Locking {
                deadline_ms: 0,
                then: AfterLock::Idle,
            },
            State::Idle,
            State::PreAlign { deadline_ms: 0 },
            State::Releasing { deadline_ms: 0 },
            State::Inserting { deadline_ms: 0 },
            State::Holding {
                until_ms: None,
                unmating: false,
            },
            State::Extracting { deadline_ms: 0 },
            State::Returning {
                deadline_ms: 0,
                ends_cycle: true,
                creeping: false,
            },
            State::BackingOff {
                deadline_ms: 0,
                target_um: 0,
            },
            State::Faulted {
                fault: FaultKind::Stopped,
            },
            State::Recovering { deadline_ms: 0 },
        ];
        for (i, s) in states.iter().enumerate() {
            assert_eq!(state_code(s) as usize, i, "{}", s.name());
        }
    }

    // -- framer --

    const S: ModbusSettings = ModbusSettings::DEFAULT; // 19 200: char 573, t1.5 860, t3.5 2006

    /// Push `bytes` back to back from `t0` (one character time apart); the last stamp.
    fn burst(f: &mut RtuFramer, bytes: &[u8], t0: u64) -> u64 {
        let c = u64::from(S.char_us());
        let mut t = t0;
        for (i, &b) in bytes.iter().enumerate() {
            t = t0 + i as u64 * c;
            f.push(b, t);
        }
        t
    }

    #[test]
    fn framer_delivers_a_frame_after_t3_5_once() {
        let mut f = RtuFramer::new(&S);
        assert_eq!(f.poll(0), None);
        let end = burst(&mut f, &[1, 2, 3, 4, 5], 10_000);
        assert_eq!(f.poll(end + 2_005), None, "not yet silent for t3.5");
        assert_eq!(f.poll(end + 2_006), Some(&[1u8, 2, 3, 4, 5][..]));
        assert_eq!(f.poll(end + 9_000), None, "once");
        assert_eq!((f.framing_errors(), f.overruns()), (0, 0));
    }

    #[test]
    fn framer_splits_frames_at_t3_5_and_counts_unpolled_ones() {
        let mut f = RtuFramer::new(&S);
        let c = u64::from(S.char_us());
        let end = burst(&mut f, &[1, 2, 3, 4], 0);
        // The next frame starts exactly t3.5 of silence later: two frames, and the
        // first was never polled.
        let end2 = burst(&mut f, &[5, 6, 7, 8], end + c + 2_006);
        assert_eq!(f.poll(end2 + 2_006), Some(&[5u8, 6, 7, 8][..]));
        assert_eq!(f.overruns(), 1);
        // A silence just under t3.5 (and over t1.5): one bad frame.
        let end3 = burst(&mut f, &[1, 2, 3, 4], end2 + 10_000);
        let end4 = burst(&mut f, &[5, 6, 7, 8], end3 + c + 2_005);
        assert_eq!(f.poll(end4 + 2_006), None);
        assert_eq!(f.framing_errors(), 1);
    }

    #[test]
    fn framer_discards_a_frame_with_a_gap_over_t1_5() {
        let mut f = RtuFramer::new(&S);
        let c = u64::from(S.char_us());
        // Silence of exactly t1.5 is allowed.
        let end = burst(&mut f, &[1, 2, 3], 0);
        let end = burst(&mut f, &[4, 5], end + c + 860);
        assert_eq!(f.poll(end + 2_006), Some(&[1u8, 2, 3, 4, 5][..]));
        // One µs more is not: the whole frame goes, and the next one is fine.
        let end = burst(&mut f, &[1, 2, 3], end + 5_000);
        let end = burst(&mut f, &[4, 5], end + c + 861);
        assert_eq!(f.poll(end + 2_006), None);
        assert_eq!(f.framing_errors(), 1);
        let end = burst(&mut f, &[9, 9, 9, 9], end + 5_000);
        assert_eq!(f.poll(end + 2_006), Some(&[9u8, 9, 9, 9][..]));
    }

    #[test]
    fn framer_discards_overlong_frames_whole_and_short_ones() {
        let mut f = RtuFramer::new(&S);
        let max = [0xA5u8; MAX_FRAME];
        let end = burst(&mut f, &max, 0);
        assert_eq!(f.poll(end + 2_006).map(<[u8]>::len), Some(MAX_FRAME));
        let mut over = [0x5Au8; MAX_FRAME + 40];
        over[0] = 1;
        let end = burst(&mut f, &over, end + 5_000);
        assert_eq!(f.poll(end + 2_006), None);
        assert_eq!(f.framing_errors(), 1);
        let end = burst(&mut f, &[1, 2, 3], end + 5_000);
        assert_eq!(f.poll(end + 2_006), None, "under 4 bytes");
        assert_eq!(f.framing_errors(), 2);
        let end = burst(&mut f, &[1, 2, 3, 4], end + 5_000);
        assert_eq!(f.poll(end + 2_006), Some(&[1u8, 2, 3, 4][..]));
    }

    #[test]
    fn framer_line_error_spoils_its_frame_only() {
        let mut f = RtuFramer::new(&S);
        let c = u64::from(S.char_us());
        let end = burst(&mut f, &[1, 2, 3], 0);
        f.line_error(end + c);
        let end = burst(&mut f, &[4, 5], end + 2 * c);
        assert_eq!(f.poll(end + 2_006), None);
        assert_eq!(f.framing_errors(), 1);
        let end = burst(&mut f, &[1, 2, 3, 4], end + 5_000);
        assert_eq!(f.poll(end + 2_006), Some(&[1u8, 2, 3, 4][..]));
    }

    #[test]
    fn framer_survives_time_going_backwards_and_huge_stamps() {
        let mut f = RtuFramer::new(&S);
        f.push(1, u64::MAX);
        f.push(2, 0);
        f.push(3, 5);
        f.push(4, u64::MAX - 1);
        assert_eq!(f.poll(u64::MAX), None, "not silent");
        assert_eq!(f.poll(0), None);
    }
}
