//! # Device identification (0x2B / MEI 0x0E)
//!
//! Conformity level 0x83 (basic, regular and extended objects; stream and individual
//! access). Read device id codes 1 (basic stream: objects 0–2), 2 (regular stream:
//! 0–0x7F), 3 (extended stream: all), 4 (one object). Objects: 0 VendorName
//! [`VENDOR_NAME`], 1 ProductCode [`PRODUCT_CODE`], 2 MajorMinorRevision (the firmware
//! version: the running image's, from its header), 4 ProductName [`PRODUCT_NAME`], 5
//! ModelName [`MODEL_NAME`], 0x80 the unit's serial number (as passed to
//! [`Server::poll`](super::Server::poll), at most [`SERIAL_OBJECT_MAX`] bytes), and the
//! images (issue 21): 0x81 the previous image's version (`none`), 0x82 the key the
//! image verifies updates with (`test` or `integrator`; `unknown` without an image
//! header: the simulators), 0x83 the last update rolled
//! back (`no`, its version, or `yes` when its version is not known), 0x84 whether the
//! running image is on trial after an update (`no`, `yes`: it confirms itself at rest
//! once the load cell answers, a reset before rolls it back; `failed`: its confirmation
//! could not be written, the next reset rolls it back; issue 31). A
//! stream that does not fit one reply sets "more follows" and the next object id; a
//! stream request for an object id that does not exist restarts at object 0 (the spec's
//! rule); an individual request for one is exception 02; any other read device id code
//! is exception 03.

use super::pdu::Reply;
use super::{exception, MAX_FRAME};
use crate::update::{version_or, ImageReport, VERSION_TEXT_MAX};

/// Object 0, VendorName, unless the commissioning file names the machine's builder
/// ([`crate::controller::Identity`]).
pub const VENDOR_NAME: &str = "docking-controller project";
/// Object 1, ProductCode (the firmware package).
pub const PRODUCT_CODE: &str = "docking-controller";
/// Object 2, MajorMinorRevision, when the image has no header (the host's simulators):
/// the build's version.
pub const REVISION: &str = env!("CARGO_PKG_VERSION");
/// Object 4, ProductName, unless the commissioning file names the product.
pub const PRODUCT_NAME: &str = "Automatic connector docking controller";
/// Object 5, ModelName.
pub const MODEL_NAME: &str = "STM32F407";
/// Object 0x80 (private): the unit's serial number.
pub const OBJECT_SERIAL: u8 = 0x80;
/// The unit serial's longest length in object 0x80, bytes (longer is cut).
pub const SERIAL_OBJECT_MAX: usize = 32;
/// Object 0x81 (private): the image this one replaced by an update.
pub const OBJECT_PREVIOUS: u8 = 0x81;
/// Object 0x82 (private): `test` when the built-in update key is the test key.
pub const OBJECT_KEY: u8 = 0x82;
/// Object 0x83 (private): the last update rolled back.
pub const OBJECT_ROLLED_BACK: u8 = 0x83;
/// Object 0x84 (private): the running image on trial (`no`, `yes`, `failed`).
pub const OBJECT_TRIAL: u8 = 0x84;
/// The conformity level: basic, regular and extended, stream and individual access.
pub const CONFORMITY: u8 = 0x83;
/// The objects, in stream order.
const OBJECTS: [u8; 10] = [
    0,
    1,
    2,
    4,
    5,
    OBJECT_SERIAL,
    OBJECT_PREVIOUS,
    OBJECT_KEY,
    OBJECT_ROLLED_BACK,
    OBJECT_TRIAL,
];

/// The images' texts.
struct Texts<'a> {
    running: &'a str,
    previous: &'a str,
    rolled: &'a str,
    key: &'static str,
    trial: &'static str,
}

fn device_object<'a>(
    id: u8,
    serial: &'a str,
    names: crate::controller::Identity,
    t: &'a Texts<'a>,
) -> Option<&'a [u8]> {
    Some(match id {
        0 => names.vendor.as_bytes(),
        1 => PRODUCT_CODE.as_bytes(),
        2 => t.running.as_bytes(),
        OBJECT_PREVIOUS => t.previous.as_bytes(),
        OBJECT_KEY => t.key.as_bytes(),
        OBJECT_ROLLED_BACK => t.rolled.as_bytes(),
        OBJECT_TRIAL => t.trial.as_bytes(),
        4 => names.product.as_bytes(),
        5 => MODEL_NAME.as_bytes(),
        OBJECT_SERIAL => {
            let b = serial.as_bytes();
            b.get(..SERIAL_OBJECT_MAX).unwrap_or(b)
        }
        _ => return None,
    })
}

/// Function 0x2B: `pdu` is the request's (function included); the reply goes to
/// `out` (the unit address is there already); returns its length without the CRC.
pub(super) fn device_identification(
    pdu: &[u8],
    serial: &str,
    names: crate::controller::Identity,
    images: &ImageReport,
    out: &mut [u8; MAX_FRAME],
) -> Reply {
    let (mut a, mut b, mut c) = (
        [0u8; VERSION_TEXT_MAX],
        [0u8; VERSION_TEXT_MAX],
        [0u8; VERSION_TEXT_MAX],
    );
    let texts = Texts {
        running: version_or(images.running, REVISION, &mut a),
        previous: version_or(images.previous, "none", &mut b),
        rolled: match (images.rolled_back, images.rolled_back_version) {
            (false, _) => "no",
            (true, v) => version_or(v, "yes", &mut c),
        },
        key: match (images.running, images.test_key) {
            (None, _) => "unknown",
            (Some(_), true) => "test",
            (Some(_), false) => "integrator",
        },
        trial: images.trial.word(),
    };
    const HEAD: usize = 8; // unit, 0x2B, 0x0E, code, conformity, more, next, count
    let &[_, mei, code, object] = pdu else {
        return match pdu.get(1) {
            Some(&0x0E) | None => Reply::Exception(exception::ILLEGAL_DATA_VALUE),
            Some(_) => Reply::Exception(exception::ILLEGAL_FUNCTION),
        };
    };
    if mei != 0x0E {
        return Reply::Exception(exception::ILLEGAL_FUNCTION);
    }
    let last_id = match code {
        1 => 0x02,
        2 => 0x7F,
        3 | 4 => 0xFF,
        _ => return Reply::Exception(exception::ILLEGAL_DATA_VALUE),
    };
    let known = device_object(object, serial, names, &texts).is_some();
    if code == 4 && !known {
        return Reply::Exception(exception::ILLEGAL_DATA_ADDRESS);
    }
    let first = if known && object <= last_id {
        object
    } else {
        0
    };
    let mut pos = HEAD;
    let mut count: u8 = 0;
    let (mut more, mut next) = (0x00, 0x00);
    for &id in OBJECTS.iter().filter(|&&id| id >= first && id <= last_id) {
        if code == 4 && id != object {
            continue;
        }
        let value = device_object(id, serial, names, &texts).unwrap_or(&[]);
        let end = pos + 2 + value.len();
        // Room for the CRC after it.
        match out.get_mut(pos..end).filter(|_| end + 2 <= MAX_FRAME) {
            Some(dst) => {
                if let Some((hdr, body)) = dst.split_first_chunk_mut::<2>() {
                    *hdr = [id, value.len() as u8];
                    body.copy_from_slice(value);
                }
            }
            None => {
                more = 0xFF;
                next = id;
                break;
            }
        }
        pos = end;
        count += 1;
    }
    if let Some(h) = out.get_mut(1..HEAD) {
        h.copy_from_slice(&[0x2B, 0x0E, code, CONFORMITY, more, next, count]);
    }
    Reply::Normal(pos)
}
