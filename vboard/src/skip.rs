//! Skipping what does not change the result: a **polling loop** recognised and jumped
//! over, its instructions and cycles charged as if they had run.
//!
//! A polling loop is a short loop whose iterations leave the machine as they found it,
//! but for registers they recompute the same way and a status register they read: the
//! flash's `SR.BSY` until an erase ends, the RCC's ready bits, a USART's `TXE`/`TC` —
//! registers the models will not change before a known instant — and `DWT_CYCCNT` for a
//! timeout. The image's sector erase is one (`board/flash.rs`, from SRAM):
//!
//! ```text
//! loop: str.w r4, [lr]      ; IWDG_KR = 0xAAAA (a reload: the same at any instant)
//!       ldr   r0, [r1]      ; FLASH_SR
//!       lsls  r5, r0, #15   ; BSY?
//!       bpl   done
//!       ldr   r5, [r2]      ; DWT_CYCCNT
//!       subs  r5, r5, r3
//!       cmp   r5, r12       ; the timeout
//!       bls   loop
//! ```
//!
//! This module is the part without the emulator: a decoder of the Thumb-2 instructions
//! such loops are made of ([`decode_block`]) and an executor of one iteration
//! ([`execute`]) over values that are either known (`Val::C`) or the cycle counter read
//! at a known instant plus a constant (`Val::S`: what `ldr; subs` of CYCCNT gives). A
//! comparison of such a value with a known one is a condition on the counter that
//! holds over an interval of its values ([`Interval`]), so the iteration at which the
//! loop stops taking the same path is computed, not searched. Anything else — a store
//! other than a watchdog reload, a load of a register that is not modelled as stable,
//! a call, an instruction outside the subset — and the loop is not skipped.
//!
//! `cpu.rs` finds the loops (the same blocks twice in a row at the same cost), checks
//! this module's prediction of the iteration it just watched against what the engine
//! did, and does the jump (`Board`'s block hook); the proof that nothing changed is the
//! comparison of every scene with `--no-skip` (`vboard/tests/skip.rs`).

/// A core register number (0–12, 13 SP, 14 LR, 15 PC).
pub type Reg = u8;

/// Why an iteration cannot be predicted (the loop is not skipped).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Abort(pub &'static str);

type Res<T> = Result<T, Abort>;

fn abort<T>(why: &'static str) -> Res<T> {
    Err(Abort(why))
}

/// A shift of a register operand.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Shift {
    /// Logical left.
    Lsl,
    /// Logical right.
    Lsr,
    /// Arithmetic right.
    Asr,
    /// Rotate right.
    Ror,
    /// Rotate right through carry by one.
    Rrx,
}

/// The second operand of a data-processing instruction.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Opnd {
    /// An immediate, and the carry its expansion gives (`None`: the carry is unchanged).
    Imm(u32, Option<bool>),
    /// A register shifted by an immediate.
    Reg(Reg, Shift, u8),
    /// A register shifted by the bottom byte of another.
    RegReg(Reg, Shift, Reg),
}

/// A data-processing operation.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AluOp {
    /// AND (TST without a destination).
    And,
    /// EOR (TEQ).
    Eor,
    /// ORR.
    Orr,
    /// ORN.
    Orn,
    /// BIC.
    Bic,
    /// MOV (and the shifts by immediate or register).
    Mov,
    /// MVN.
    Mvn,
    /// ADD (CMN).
    Add,
    /// ADC.
    Adc,
    /// SUB (CMP).
    Sub,
    /// SBC.
    Sbc,
    /// RSB.
    Rsb,
    /// MUL.
    Mul,
}

/// An addressing mode's offset.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Off {
    /// An immediate: offset, pre-indexed (`false`: post), write back.
    Imm(i32, bool, bool),
    /// A register shifted left.
    Reg(Reg, u8),
}

/// One instruction of the subset.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Op {
    /// `d = n op m` (no `d`: a compare or test; no `n`: MOV/MVN), flags if `s`.
    Alu {
        /// The operation.
        op: AluOp,
        /// Destination.
        d: Option<Reg>,
        /// First operand.
        n: Option<Reg>,
        /// Second operand.
        m: Opnd,
        /// Sets the flags.
        s: bool,
    },
    /// `d = m` zero- or sign-extended from a byte or halfword after rotating right.
    Ext {
        /// Destination.
        d: Reg,
        /// Source.
        m: Reg,
        /// Rotation, bits.
        rot: u8,
        /// Bits kept (8 or 16).
        bits: u8,
        /// Sign-extended.
        signed: bool,
    },
    /// `d = (n >> lsb) & (2^width - 1)`, sign-extended if `signed`.
    Bfx {
        /// Destination.
        d: Reg,
        /// Source.
        n: Reg,
        /// First bit.
        lsb: u8,
        /// Width, bits.
        width: u8,
        /// SBFX.
        signed: bool,
    },
    /// MOVW (`top`: MOVT, the upper halfword).
    Mov16 {
        /// Destination.
        d: Reg,
        /// The halfword.
        imm: u16,
        /// MOVT.
        top: bool,
    },
    /// A load of `size` bytes into `t` from `[n + off]` (`n` 15: PC-relative).
    Load {
        /// Destination.
        t: Reg,
        /// Base.
        n: Reg,
        /// Offset.
        off: Off,
        /// Bytes.
        size: u8,
        /// Sign-extended.
        signed: bool,
    },
    /// A store of the low `size` bytes of `t` to `[n + off]`.
    Store {
        /// Source.
        t: Reg,
        /// Base.
        n: Reg,
        /// Offset.
        off: Off,
        /// Bytes.
        size: u8,
    },
    /// A branch to `target` if `cond` holds (14: always).
    B {
        /// Condition (0–14).
        cond: u8,
        /// Target.
        target: u32,
    },
    /// CBZ / CBNZ (`nz`).
    Cbz {
        /// Register tested.
        n: Reg,
        /// CBNZ.
        nz: bool,
        /// Target.
        target: u32,
    },
    /// IT: the first condition and the mask.
    It {
        /// First condition.
        first: u8,
        /// Mask.
        mask: u8,
    },
    /// No operation (NOP, YIELD, a DMB/DSB/ISB: memory order changes nothing here).
    Nop,
}

/// A decoded instruction: address, length (2 or 4) and operation.
pub type Insn = (u32, u8, Op);

fn sext(v: u32, bits: u32) -> u32 {
    let s = 32 - bits;
    (((v << s) as i32) >> s) as u32
}

fn expand_imm(imm12: u32) -> (u32, Option<bool>) {
    let imm8 = imm12 & 0xFF;
    if imm12 >> 10 == 0 {
        let v = match (imm12 >> 8) & 3 {
            0 => imm8,
            1 => imm8 << 16 | imm8,
            2 => imm8 << 24 | imm8 << 8,
            _ => imm8 * 0x0101_0101,
        };
        (v, None)
    } else {
        let unrot = 0x80 | (imm12 & 0x7F);
        let v = unrot.rotate_right(imm12 >> 7);
        (v, Some(v >> 31 != 0))
    }
}

fn imm_shift(ty: u32, imm5: u32) -> (Shift, u8) {
    match ty {
        0 => (Shift::Lsl, imm5 as u8),
        1 => (Shift::Lsr, if imm5 == 0 { 32 } else { imm5 as u8 }),
        2 => (Shift::Asr, if imm5 == 0 { 32 } else { imm5 as u8 }),
        _ if imm5 == 0 => (Shift::Rrx, 1),
        _ => (Shift::Ror, imm5 as u8),
    }
}

/// Decode the instructions of a translated block (`bytes` at `addr`). `Err`: an
/// instruction outside the subset.
pub fn decode_block(bytes: &[u8], addr: u32) -> Res<Vec<Insn>> {
    let mut out = Vec::new();
    let mut i = 0usize;
    while i + 1 < bytes.len() {
        let hw = u32::from(u16::from_le_bytes([bytes[i], bytes[i + 1]]));
        let at = addr + i as u32;
        if hw >> 11 >= 0b11101 {
            let Some(b) = bytes.get(i + 2..i + 4) else {
                return abort("a 32-bit instruction cut by the block's end");
            };
            let hw2 = u32::from(u16::from_le_bytes([b[0], b[1]]));
            out.push((at, 4, decode32(hw, hw2, at)?));
            i += 4;
        } else {
            out.push((at, 2, decode16(hw, at)?));
            i += 2;
        }
    }
    Ok(out)
}

fn decode16(hw: u32, at: u32) -> Res<Op> {
    let r = |shift: u32| ((hw >> shift) & 7) as Reg;
    let pc4 = at.wrapping_add(4);
    Ok(match hw >> 11 {
        // LSL/LSR/ASR (immediate).
        0..=2 => {
            let (sh, amount) = imm_shift(hw >> 11, (hw >> 6) & 31);
            Op::Alu {
                op: AluOp::Mov,
                d: Some(r(0)),
                n: None,
                m: Opnd::Reg(r(3), sh, amount),
                s: true,
            }
        }
        // ADD/SUB register or 3-bit immediate.
        3 => {
            let op = if hw & (1 << 9) != 0 {
                AluOp::Sub
            } else {
                AluOp::Add
            };
            let m = if hw & (1 << 10) != 0 {
                Opnd::Imm((hw >> 6) & 7, None)
            } else {
                Opnd::Reg(r(6), Shift::Lsl, 0)
            };
            Op::Alu {
                op,
                d: Some(r(0)),
                n: Some(r(3)),
                m,
                s: true,
            }
        }
        // MOV/CMP/ADD/SUB 8-bit immediate.
        4..=7 => {
            let d = r(8);
            let m = Opnd::Imm(hw & 0xFF, None);
            match (hw >> 11) & 3 {
                0 => Op::Alu {
                    op: AluOp::Mov,
                    d: Some(d),
                    n: None,
                    m,
                    s: true,
                },
                1 => Op::Alu {
                    op: AluOp::Sub,
                    d: None,
                    n: Some(d),
                    m,
                    s: true,
                },
                2 => Op::Alu {
                    op: AluOp::Add,
                    d: Some(d),
                    n: Some(d),
                    m,
                    s: true,
                },
                _ => Op::Alu {
                    op: AluOp::Sub,
                    d: Some(d),
                    n: Some(d),
                    m,
                    s: true,
                },
            }
        }
        8 => {
            if hw & (1 << 10) == 0 {
                // Data processing on two low registers.
                let (dn, m) = (r(0), r(3));
                let reg = Opnd::Reg(m, Shift::Lsl, 0);
                let alu = |op, d: Option<Reg>, n: Option<Reg>, mo| Op::Alu {
                    op,
                    d,
                    n,
                    m: mo,
                    s: true,
                };
                match (hw >> 6) & 0xF {
                    0 => alu(AluOp::And, Some(dn), Some(dn), reg),
                    1 => alu(AluOp::Eor, Some(dn), Some(dn), reg),
                    2 => alu(AluOp::Mov, Some(dn), None, Opnd::RegReg(dn, Shift::Lsl, m)),
                    3 => alu(AluOp::Mov, Some(dn), None, Opnd::RegReg(dn, Shift::Lsr, m)),
                    4 => alu(AluOp::Mov, Some(dn), None, Opnd::RegReg(dn, Shift::Asr, m)),
                    5 => alu(AluOp::Adc, Some(dn), Some(dn), reg),
                    6 => alu(AluOp::Sbc, Some(dn), Some(dn), reg),
                    7 => alu(AluOp::Mov, Some(dn), None, Opnd::RegReg(dn, Shift::Ror, m)),
                    8 => alu(AluOp::And, None, Some(dn), reg),
                    9 => alu(AluOp::Rsb, Some(dn), Some(m), Opnd::Imm(0, None)),
                    10 => alu(AluOp::Sub, None, Some(dn), reg),
                    11 => alu(AluOp::Add, None, Some(dn), reg),
                    12 => alu(AluOp::Orr, Some(dn), Some(dn), reg),
                    13 => alu(AluOp::Mul, Some(dn), Some(dn), reg),
                    14 => alu(AluOp::Bic, Some(dn), Some(dn), reg),
                    _ => alu(AluOp::Mvn, Some(dn), None, reg),
                }
            } else {
                // Special data processing on any registers (no flags but CMP).
                let dn = (((hw >> 7) & 1) << 3 | (hw & 7)) as Reg;
                let m = ((hw >> 3) & 0xF) as Reg;
                match (hw >> 8) & 3 {
                    0 if dn != 15 => Op::Alu {
                        op: AluOp::Add,
                        d: Some(dn),
                        n: Some(dn),
                        m: Opnd::Reg(m, Shift::Lsl, 0),
                        s: false,
                    },
                    1 => Op::Alu {
                        op: AluOp::Sub,
                        d: None,
                        n: Some(dn),
                        m: Opnd::Reg(m, Shift::Lsl, 0),
                        s: true,
                    },
                    2 if dn != 15 => Op::Alu {
                        op: AluOp::Mov,
                        d: Some(dn),
                        n: None,
                        m: Opnd::Reg(m, Shift::Lsl, 0),
                        s: false,
                    },
                    _ => return abort("a branch through a register"),
                }
            }
        }
        // LDR (literal).
        9 => Op::Load {
            t: r(8),
            n: 15,
            off: Off::Imm(((hw & 0xFF) * 4) as i32, true, false),
            size: 4,
            signed: false,
        },
        // Load/store, register offset.
        10 | 11 => {
            let off = Off::Reg(r(6), 0);
            let (t, n) = (r(0), r(3));
            match (hw >> 9) & 7 {
                0 => Op::Store { t, n, off, size: 4 },
                1 => Op::Store { t, n, off, size: 2 },
                2 => Op::Store { t, n, off, size: 1 },
                3 => Op::Load {
                    t,
                    n,
                    off,
                    size: 1,
                    signed: true,
                },
                4 => Op::Load {
                    t,
                    n,
                    off,
                    size: 4,
                    signed: false,
                },
                5 => Op::Load {
                    t,
                    n,
                    off,
                    size: 2,
                    signed: false,
                },
                6 => Op::Load {
                    t,
                    n,
                    off,
                    size: 1,
                    signed: false,
                },
                _ => Op::Load {
                    t,
                    n,
                    off,
                    size: 2,
                    signed: true,
                },
            }
        }
        // Load/store word or byte, immediate offset.
        12..=15 => {
            let byte = hw & (1 << 12) != 0;
            let imm5 = (hw >> 6) & 31;
            let (size, off) = if byte { (1, imm5) } else { (4, imm5 * 4) };
            let off = Off::Imm(off as i32, true, false);
            let (t, n) = (r(0), r(3));
            if hw & (1 << 11) != 0 {
                Op::Load {
                    t,
                    n,
                    off,
                    size,
                    signed: false,
                }
            } else {
                Op::Store { t, n, off, size }
            }
        }
        // Load/store halfword, immediate offset.
        16 | 17 => {
            let off = Off::Imm((((hw >> 6) & 31) * 2) as i32, true, false);
            let (t, n) = (r(0), r(3));
            if hw & (1 << 11) != 0 {
                Op::Load {
                    t,
                    n,
                    off,
                    size: 2,
                    signed: false,
                }
            } else {
                Op::Store { t, n, off, size: 2 }
            }
        }
        // Load/store SP-relative.
        18 | 19 => {
            let off = Off::Imm(((hw & 0xFF) * 4) as i32, true, false);
            if hw & (1 << 11) != 0 {
                Op::Load {
                    t: r(8),
                    n: 13,
                    off,
                    size: 4,
                    signed: false,
                }
            } else {
                Op::Store {
                    t: r(8),
                    n: 13,
                    off,
                    size: 4,
                }
            }
        }
        // ADR / ADD Rd, SP, #imm.
        20 | 21 => {
            let imm = (hw & 0xFF) * 4;
            if hw & (1 << 11) == 0 {
                Op::Alu {
                    op: AluOp::Mov,
                    d: Some(r(8)),
                    n: None,
                    m: Opnd::Imm((pc4 & !3).wrapping_add(imm), None),
                    s: false,
                }
            } else {
                Op::Alu {
                    op: AluOp::Add,
                    d: Some(r(8)),
                    n: Some(13),
                    m: Opnd::Imm(imm, None),
                    s: false,
                }
            }
        }
        // Miscellaneous.
        22 | 23 => {
            if hw & 0xFF00 == 0xB000 {
                let imm = (hw & 0x7F) * 4;
                Op::Alu {
                    op: if hw & 0x80 != 0 {
                        AluOp::Sub
                    } else {
                        AluOp::Add
                    },
                    d: Some(13),
                    n: Some(13),
                    m: Opnd::Imm(imm, None),
                    s: false,
                }
            } else if hw & 0xF500 == 0xB100 {
                let imm = ((hw >> 9) & 1) << 6 | ((hw >> 3) & 31) << 1;
                Op::Cbz {
                    n: r(0),
                    nz: hw & (1 << 11) != 0,
                    target: pc4.wrapping_add(imm),
                }
            } else if hw & 0xFF00 == 0xB200 {
                let (d, m) = (r(0), r(3));
                let (bits, signed) = match (hw >> 6) & 3 {
                    0 => (16, true),
                    1 => (8, true),
                    2 => (16, false),
                    _ => (8, false),
                };
                Op::Ext {
                    d,
                    m,
                    rot: 0,
                    bits,
                    signed,
                }
            } else if hw & 0xFF00 == 0xBF00 && hw & 0xF != 0 {
                Op::It {
                    first: ((hw >> 4) & 0xF) as u8,
                    mask: (hw & 0xF) as u8,
                }
            } else if hw == 0xBF00 || hw == 0xBF10 {
                Op::Nop
            } else {
                return abort("push, pop, a hint or another miscellaneous instruction");
            }
        }
        // Conditional branch (0b1101 cccc), UDF and SVC excluded.
        26 | 27 => {
            let cond = (hw >> 8) & 0xF;
            if cond >= 14 {
                return abort("udf or svc");
            }
            Op::B {
                cond: cond as u8,
                target: pc4.wrapping_add(sext((hw & 0xFF) << 1, 9)),
            }
        }
        // Unconditional branch.
        28 => Op::B {
            cond: 14,
            target: pc4.wrapping_add(sext((hw & 0x7FF) << 1, 12)),
        },
        _ => return abort("load/store multiple, svc or another 16-bit instruction"),
    })
}

fn dp_op(op: u32, d: Reg, n: Reg, s: bool, m: Opnd) -> Res<Op> {
    // The op table of "data processing (modified immediate)" and "(shifted register)".
    let alu = |op, d: Option<Reg>, n: Option<Reg>| Op::Alu { op, d, n, m, s };
    let cmp = d == 15 && s;
    Ok(match op {
        0 if cmp => alu(AluOp::And, None, Some(n)),
        0 => alu(AluOp::And, Some(d), Some(n)),
        1 => alu(AluOp::Bic, Some(d), Some(n)),
        2 if n == 15 => alu(AluOp::Mov, Some(d), None),
        2 => alu(AluOp::Orr, Some(d), Some(n)),
        3 if n == 15 => alu(AluOp::Mvn, Some(d), None),
        3 => alu(AluOp::Orn, Some(d), Some(n)),
        4 if cmp => alu(AluOp::Eor, None, Some(n)),
        4 => alu(AluOp::Eor, Some(d), Some(n)),
        8 if cmp => alu(AluOp::Add, None, Some(n)),
        8 => alu(AluOp::Add, Some(d), Some(n)),
        10 => alu(AluOp::Adc, Some(d), Some(n)),
        11 => alu(AluOp::Sbc, Some(d), Some(n)),
        13 if cmp => alu(AluOp::Sub, None, Some(n)),
        13 => alu(AluOp::Sub, Some(d), Some(n)),
        14 => alu(AluOp::Rsb, Some(d), Some(n)),
        _ => return abort("PKHBT/PKHTB or an undefined data-processing operation"),
    })
}

fn decode32(hw1: u32, hw2: u32, at: u32) -> Res<Op> {
    let pc4 = at.wrapping_add(4);
    let rn = (hw1 & 0xF) as Reg;
    let rd = ((hw2 >> 8) & 0xF) as Reg;
    let rt = ((hw2 >> 12) & 0xF) as Reg;
    // Data processing, modified immediate.
    if hw1 & 0xFA00 == 0xF000 && hw2 & 0x8000 == 0 {
        let imm12 = ((hw1 >> 10) & 1) << 11 | ((hw2 >> 12) & 7) << 8 | (hw2 & 0xFF);
        let (v, c) = expand_imm(imm12);
        let s = hw1 & (1 << 4) != 0;
        let op = dp_op((hw1 >> 5) & 0xF, rd, rn, s, Opnd::Imm(v, c))?;
        return no_pc(op);
    }
    // Data processing, plain binary immediate.
    if hw1 & 0xFA00 == 0xF200 && hw2 & 0x8000 == 0 {
        let imm12 = ((hw1 >> 10) & 1) << 11 | ((hw2 >> 12) & 7) << 8 | (hw2 & 0xFF);
        let imm16 = (hw1 & 0xF) << 12 | imm12;
        let lsb = (((hw2 >> 12) & 7) << 2 | ((hw2 >> 6) & 3)) as u8;
        let w = (hw2 & 0x1F) as u8 + 1;
        let op = match (hw1 >> 4) & 0x1F {
            0 if rn == 15 => Op::Alu {
                op: AluOp::Mov,
                d: Some(rd),
                n: None,
                m: Opnd::Imm((pc4 & !3).wrapping_add(imm12), None),
                s: false,
            },
            0 => Op::Alu {
                op: AluOp::Add,
                d: Some(rd),
                n: Some(rn),
                m: Opnd::Imm(imm12, None),
                s: false,
            },
            4 => Op::Mov16 {
                d: rd,
                imm: imm16 as u16,
                top: false,
            },
            10 if rn == 15 => Op::Alu {
                op: AluOp::Mov,
                d: Some(rd),
                n: None,
                m: Opnd::Imm((pc4 & !3).wrapping_sub(imm12), None),
                s: false,
            },
            10 => Op::Alu {
                op: AluOp::Sub,
                d: Some(rd),
                n: Some(rn),
                m: Opnd::Imm(imm12, None),
                s: false,
            },
            12 => Op::Mov16 {
                d: rd,
                imm: imm16 as u16,
                top: true,
            },
            20 | 28 if lsb as u32 + w as u32 <= 32 => Op::Bfx {
                d: rd,
                n: rn,
                lsb,
                width: w,
                signed: (hw1 >> 4) & 0x1F == 20,
            },
            _ => return abort("SSAT, USAT, BFI or a bitfield out of range"),
        };
        return no_pc(op);
    }
    // Branches and miscellaneous control.
    if hw1 & 0xF800 == 0xF000 && hw2 & 0x8000 != 0 {
        let s = (hw1 >> 10) & 1;
        let (j1, j2) = ((hw2 >> 13) & 1, (hw2 >> 11) & 1);
        return match hw2 & 0xD000 {
            0x9000 => {
                let (i1, i2) = (1 ^ j1 ^ s, 1 ^ j2 ^ s);
                let imm = s << 24 | i1 << 23 | i2 << 22 | (hw1 & 0x3FF) << 12 | (hw2 & 0x7FF) << 1;
                Ok(Op::B {
                    cond: 14,
                    target: pc4.wrapping_add(sext(imm, 25)),
                })
            }
            0x8000 => {
                let cond = (hw1 >> 6) & 0xF;
                if cond >= 14 {
                    // NOP.W and the memory barriers (`dmb`, `dsb`, `isb`) are allowed:
                    // the model has no write buffer or pipeline for them to change.
                    let barrier = hw1 == 0xF3BF && matches!(hw2 & 0xFFF0, 0x8F40 | 0x8F50 | 0x8F60);
                    return if hw1 == 0xF3AF && hw2 == 0x8000 || barrier {
                        Ok(Op::Nop)
                    } else {
                        abort("MSR, MRS, CPS or another control instruction")
                    };
                }
                let imm = s << 20 | j2 << 19 | j1 << 18 | (hw1 & 0x3F) << 12 | (hw2 & 0x7FF) << 1;
                Ok(Op::B {
                    cond: cond as u8,
                    target: pc4.wrapping_add(sext(imm, 21)),
                })
            }
            _ => abort("a call"),
        };
    }
    // Load/store single data item.
    if hw1 & 0xFE00 == 0xF800 {
        let signed = hw1 & (1 << 8) != 0;
        let size = 1u8 << ((hw1 >> 5) & 3);
        let load = hw1 & (1 << 4) != 0;
        if size == 8 || (signed && !load) {
            return abort("an undefined load/store");
        }
        if load && rt == 15 {
            return abort("a load into PC, or a preload");
        }
        let off = if rn == 15 {
            // Literal: U is bit 7.
            let imm = (hw2 & 0xFFF) as i32;
            Off::Imm(if hw1 & (1 << 7) != 0 { imm } else { -imm }, true, false)
        } else if hw1 & (1 << 7) != 0 {
            Off::Imm((hw2 & 0xFFF) as i32, true, false)
        } else if hw2 & (1 << 11) != 0 {
            let (p, u, w) = (
                hw2 & (1 << 10) != 0,
                hw2 & (1 << 9) != 0,
                hw2 & (1 << 8) != 0,
            );
            if p && u && !w {
                return abort("an unprivileged load/store");
            }
            if !p && !w {
                return abort("an undefined load/store");
            }
            let imm = (hw2 & 0xFF) as i32;
            Off::Imm(if u { imm } else { -imm }, p, w)
        } else if hw2 & 0x0FC0 == 0 {
            Off::Reg((hw2 & 0xF) as Reg, ((hw2 >> 4) & 3) as u8)
        } else {
            return abort("an undefined load/store");
        };
        if let Off::Imm(_, _, true) = off {
            if rn == rt {
                return abort("a write-back to the register loaded");
            }
        }
        return Ok(if load {
            Op::Load {
                t: rt,
                n: rn,
                off,
                size,
                signed,
            }
        } else {
            if rt == 15 || rn == 15 {
                return abort("a store of PC or PC-relative");
            }
            Op::Store {
                t: rt,
                n: rn,
                off,
                size,
            }
        });
    }
    // Data processing, shifted register.
    if hw1 & 0xFE00 == 0xEA00 {
        let imm5 = ((hw2 >> 12) & 7) << 2 | ((hw2 >> 6) & 3);
        let (sh, amount) = imm_shift((hw2 >> 4) & 3, imm5);
        let m = Opnd::Reg((hw2 & 0xF) as Reg, sh, amount);
        let s = hw1 & (1 << 4) != 0;
        let op = dp_op((hw1 >> 5) & 0xF, rd, rn, s, m)?;
        return no_pc(op);
    }
    // Data processing, register: shifts by a register, extends.
    if hw1 & 0xFF80 == 0xFA00 && hw2 & 0xF000 == 0xF000 {
        let rm = (hw2 & 0xF) as Reg;
        if hw2 & 0x00F0 == 0 {
            let sh = [Shift::Lsl, Shift::Lsr, Shift::Asr, Shift::Ror][((hw1 >> 5) & 3) as usize];
            return no_pc(Op::Alu {
                op: AluOp::Mov,
                d: Some(rd),
                n: None,
                m: Opnd::RegReg(rn, sh, rm),
                s: hw1 & (1 << 4) != 0,
            });
        }
        if hw2 & 0x0080 != 0 && rn == 15 {
            let (bits, signed) = match (hw1 >> 4) & 7 {
                0 => (16, true),
                1 => (16, false),
                4 => (8, true),
                5 => (8, false),
                _ => return abort("an extend of another width"),
            };
            return no_pc(Op::Ext {
                d: rd,
                m: rm,
                rot: (((hw2 >> 4) & 3) * 8) as u8,
                bits,
                signed,
            });
        }
        return abort("an extend-and-add or another register operation");
    }
    abort("a 32-bit instruction outside the subset")
}

/// A data-processing instruction that writes PC or SP from anything but SP is refused.
fn no_pc(op: Op) -> Res<Op> {
    match op {
        Op::Alu { d: Some(15), .. }
        | Op::Ext { d: 15, .. }
        | Op::Bfx { d: 15, .. }
        | Op::Mov16 { d: 15, .. } => abort("a write to PC"),
        o => Ok(o),
    }
}

/// A value: known, or the cycle counter read number `sym` plus `k` (mod 2^32).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Val {
    /// Known.
    C(u32),
    /// `CYCCNT` as read by the iteration's read `sym`, plus `k`.
    S {
        /// Which read.
        sym: u8,
        /// Added.
        k: u32,
    },
}

/// A flag: known, or the flag of the subtraction `subs[i]` (an `x - y` with `x` a
/// [`Val::S`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Flag {
    /// Known.
    C(bool),
    /// Of the subtraction `i`.
    Sub(u8),
}

/// The values of a counter `c` (mod 2^32) for which a condition holds: `lo`, `lo + 1`,
/// … `len` of them, wrapping.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Interval {
    /// First value.
    pub lo: u32,
    /// How many (0 to 2^32).
    pub len: u64,
}

const FULL: u64 = 1 << 32;

impl Interval {
    /// Whether `c` is in it.
    pub fn contains(&self, c: u32) -> bool {
        u64::from(c.wrapping_sub(self.lo)) < self.len
    }

    /// The values not in it.
    pub fn complement(&self) -> Self {
        Self {
            lo: self.lo.wrapping_add(self.len as u32),
            len: FULL - self.len,
        }
    }

    /// From `c` (in it), how many increments leave it (`None`: never).
    pub fn exit_distance(&self, c: u32) -> Option<u64> {
        (self.len < FULL).then(|| self.len - u64::from(c.wrapping_sub(self.lo)))
    }

    /// The interval of `c` for which `cond` holds on the flags of `(c + k) - y`.
    fn of_sub(cond: u8, k: u32, y: u32) -> Option<Self> {
        const H: u32 = 1 << 31;
        let big_y = y ^ H;
        let x = |lo: u32, len: u64| Self {
            lo: lo.wrapping_sub(k),
            len,
        };
        Some(match cond {
            0 => x(y, 1),
            1 => x(y, 1).complement(),
            2 => x(y, FULL - u64::from(y)),
            3 => x(0, u64::from(y)),
            4 => x(y.wrapping_add(H), 1 << 31),
            5 => x(y, 1 << 31),
            8 => x(y.wrapping_add(1), FULL - 1 - u64::from(y)),
            9 => x(0, u64::from(y) + 1),
            10 => x(y, FULL - u64::from(big_y)),
            11 => x(H, u64::from(big_y)),
            12 => x(y.wrapping_add(1), FULL - 1 - u64::from(big_y)),
            13 => x(H, u64::from(big_y) + 1),
            14 => x(0, FULL),
            _ => return None,
        })
    }
}

/// A condition on the counter the path of an iteration depends on: the path is the same
/// as long as read `sym`'s value stays in `holds`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Constraint {
    /// Which read.
    pub sym: u8,
    /// The values for which the path is the same.
    pub holds: Interval,
}

/// What a load found.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Loaded {
    /// A value the models keep as it is until the iteration is skipped no further.
    Val(u32),
    /// The cycle counter: its value at this read.
    Cycles(u32),
}

/// Memory and peripherals as the executor sees them.
pub trait Env {
    /// A load of `size` bytes at `addr` by an instruction of block `blk`.
    fn load(&mut self, addr: u32, size: u8, blk: usize) -> Res<Loaded>;
    /// A store of `size` bytes of `value` at `addr` by an instruction of block `blk`.
    fn store(&mut self, addr: u32, size: u8, value: u32, blk: usize) -> Res<()>;
}

/// The outcome of one iteration.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Outcome {
    /// R0–R14 at its end.
    pub regs: [Val; 15],
    /// N, Z, C, V at its end.
    pub flags: [Flag; 4],
    /// The subtractions `Flag::Sub` refers to: (read, k, y).
    pub subs: Vec<(u8, u32, u32)>,
    /// The counter's value at each read (`Val::S`'s `sym` indexes it).
    pub sym_vals: Vec<u32>,
    /// Registers read before the iteration wrote them (bit per register).
    pub live_in: u16,
    /// Flags read before it wrote them (bit 3 N, 2 Z, 1 C, 0 V).
    pub flags_live_in: u8,
    /// What the path depends on.
    pub constraints: Vec<Constraint>,
    /// Instructions executed (a skipped IT-conditional one included: it costs its
    /// cycle).
    pub insns: u64,
}

impl Outcome {
    /// R0–R14 and the flags (N, Z, C, V as bits 31–28) for the counter reads `c`
    /// (`None`: a value depends on a read not given).
    pub fn concrete(&self, c: &[u32]) -> Option<([u32; 15], u32)> {
        let val = |v: Val| match v {
            Val::C(x) => Some(x),
            Val::S { sym, k } => c.get(sym as usize).map(|&x| x.wrapping_add(k)),
        };
        let mut regs = [0u32; 15];
        for (r, v) in regs.iter_mut().zip(self.regs) {
            *r = val(v)?;
        }
        let mut nzcv = 0;
        for (i, f) in self.flags.iter().enumerate() {
            let bit = match *f {
                Flag::C(b) => b,
                Flag::Sub(s) => {
                    let (sym, k, y) = *self.subs.get(s as usize)?;
                    let x = c.get(sym as usize)?.wrapping_add(k);
                    sub_flags(x, y)[i]
                }
            };
            nzcv |= u32::from(bit) << (31 - i);
        }
        Some((regs, nzcv))
    }
}

fn sub_flags(x: u32, y: u32) -> [bool; 4] {
    let (r, c, v) = add_with_carry(x, !y, true);
    [r >> 31 != 0, r == 0, c, v]
}

fn add_with_carry(x: u32, y: u32, c: bool) -> (u32, bool, bool) {
    let u = u64::from(x) + u64::from(y) + u64::from(c);
    let r = u as u32;
    let v = ((x ^ r) & (y ^ r)) >> 31 != 0;
    (r, u >> 32 != 0, v)
}

fn shift_c(v: u32, sh: Shift, amount: u32, carry: bool) -> (u32, bool) {
    if amount == 0 && sh != Shift::Rrx {
        return (v, carry);
    }
    match sh {
        Shift::Lsl => match amount {
            1..=31 => (v << amount, (v >> (32 - amount)) & 1 != 0),
            32 => (0, v & 1 != 0),
            _ => (0, false),
        },
        Shift::Lsr => match amount {
            1..=31 => (v >> amount, (v >> (amount - 1)) & 1 != 0),
            32 => (0, v >> 31 != 0),
            _ => (0, false),
        },
        Shift::Asr => {
            let a = amount.min(32);
            let r = if a == 32 {
                ((v as i32) >> 31) as u32
            } else {
                ((v as i32) >> a) as u32
            };
            (r, ((v as i32) >> (a - 1).min(31)) & 1 != 0)
        }
        Shift::Ror => {
            let r = v.rotate_right(amount % 32);
            (r, r >> 31 != 0)
        }
        Shift::Rrx => ((u32::from(carry) << 31) | (v >> 1), v & 1 != 0),
    }
}

struct Exec<'a> {
    regs: [Val; 15],
    flags: [Flag; 4],
    subs: Vec<(u8, u32, u32)>,
    sym_vals: Vec<u32>,
    written: u16,
    live_in: u16,
    flags_written: u8,
    flags_live_in: u8,
    constraints: Vec<Constraint>,
    env: &'a mut dyn Env,
    /// ITSTATE (the IT block in progress: condition and mask, as the architecture keeps
    /// them).
    it: u8,
}

impl Exec<'_> {
    fn reg(&mut self, r: Reg, pc: u32) -> Val {
        if r == 15 {
            return Val::C(pc.wrapping_add(4));
        }
        if self.written & (1 << r) == 0 {
            self.live_in |= 1 << r;
        }
        self.regs[r as usize]
    }

    fn known(&mut self, r: Reg, pc: u32) -> Res<u32> {
        match self.reg(r, pc) {
            Val::C(v) => Ok(v),
            Val::S { .. } => abort("a counter value used as other than x + k or x - y"),
        }
    }

    fn set(&mut self, r: Reg, v: Val) -> Res<()> {
        if r > 14 {
            return abort("a write to PC");
        }
        self.written |= 1 << r;
        self.regs[r as usize] = v;
        Ok(())
    }

    fn flag(&mut self, i: usize) -> Flag {
        if self.flags_written & (8 >> i) == 0 {
            self.flags_live_in |= 8 >> i;
        }
        self.flags[i]
    }

    fn known_flag(&mut self, i: usize) -> Res<bool> {
        match self.flag(i) {
            Flag::C(b) => Ok(b),
            Flag::Sub(_) => abort("a carry from a counter comparison used in arithmetic"),
        }
    }

    fn set_flag(&mut self, i: usize, f: Flag) {
        self.flags_written |= 8 >> i;
        self.flags[i] = f;
    }

    /// Whether `cond` holds; records the interval it holds over when it depends on the
    /// counter.
    fn cond(&mut self, cond: u8) -> Res<bool> {
        if cond == 14 {
            return Ok(true);
        }
        let need: &[usize] = match cond {
            0 | 1 => &[1],
            2 | 3 => &[2],
            4 | 5 => &[0],
            6 | 7 => &[3],
            8 | 9 => &[1, 2],
            10 | 11 => &[0, 3],
            _ => &[0, 1, 3],
        };
        let fl: Vec<Flag> = need.iter().map(|&i| self.flag(i)).collect();
        let get = |i: usize| {
            need.iter().position(|&n| n == i).and_then(|p| match fl[p] {
                Flag::C(b) => Some(b),
                Flag::Sub(_) => None,
            })
        };
        if fl.iter().all(|f| matches!(f, Flag::C(_))) {
            let (n, z, c, v) = (
                get(0).unwrap_or(false),
                get(1).unwrap_or(false),
                get(2).unwrap_or(false),
                get(3).unwrap_or(false),
            );
            return Ok(eval_cond(cond, n, z, c, v));
        }
        let Flag::Sub(s) = fl[0] else {
            return abort("a condition on flags of a comparison and of something else");
        };
        if fl.iter().any(|&f| f != Flag::Sub(s)) {
            return abort("a condition on flags of two comparisons");
        }
        let (sym, k, y) = self.subs[s as usize];
        let Some(iv) = Interval::of_sub(cond, k, y) else {
            return abort("an overflow condition on a counter comparison");
        };
        let c = self.sym_vals[sym as usize];
        let holds = iv.contains(c);
        self.constraints.push(Constraint {
            sym,
            holds: if holds { iv } else { iv.complement() },
        });
        Ok(holds)
    }

    fn operand(&mut self, m: Opnd, pc: u32) -> Res<(Val, Option<bool>)> {
        Ok(match m {
            Opnd::Imm(v, c) => (Val::C(v), c),
            Opnd::Reg(r, Shift::Lsl, 0) => (self.reg(r, pc), None),
            Opnd::Reg(r, sh, a) => {
                let v = self.known(r, pc)?;
                let c = if sh == Shift::Rrx {
                    self.known_flag(2)?
                } else {
                    false
                };
                let (x, co) = shift_c(v, sh, u32::from(a), c);
                (Val::C(x), Some(co))
            }
            Opnd::RegReg(r, sh, s) => {
                let v = self.known(r, pc)?;
                let a = self.known(s, pc)? & 0xFF;
                if a == 0 {
                    (Val::C(v), None)
                } else {
                    let (x, co) = shift_c(v, sh, a, false);
                    (Val::C(x), Some(co))
                }
            }
        })
    }

    fn address(&mut self, n: Reg, off: Off, pc: u32) -> Res<(u32, Option<u32>)> {
        let base = if n == 15 {
            pc.wrapping_add(4) & !3
        } else {
            self.known(n, pc)?
        };
        Ok(match off {
            Off::Imm(i, pre, wb) => {
                let moved = base.wrapping_add(i as u32);
                (if pre { moved } else { base }, wb.then_some(moved))
            }
            Off::Reg(m, sh) => (base.wrapping_add(self.known(m, pc)? << sh), None),
        })
    }

    fn alu(
        &mut self,
        op: AluOp,
        d: Option<Reg>,
        n: Option<Reg>,
        m: Opnd,
        s: bool,
        pc: u32,
    ) -> Res<()> {
        let (mv, shift_carry) = self.operand(m, pc)?;
        let nv = n.map(|r| self.reg(r, pc));
        // The counter's value goes through additions and subtractions of known values.
        let symbolic = matches!(mv, Val::S { .. }) || matches!(nv, Some(Val::S { .. }));
        if symbolic {
            let out = match (op, nv, mv) {
                (AluOp::Mov, None, v @ Val::S { .. }) if !s => v,
                (AluOp::Add, Some(Val::S { sym, k }), Val::C(y))
                | (AluOp::Add, Some(Val::C(y)), Val::S { sym, k })
                    if !s =>
                {
                    Val::S {
                        sym,
                        k: k.wrapping_add(y),
                    }
                }
                (AluOp::Sub, Some(Val::S { sym, k }), Val::C(y)) => {
                    if s {
                        let i = self.subs.len() as u8;
                        self.subs.push((sym, k, y));
                        for f in 0..4 {
                            self.set_flag(f, Flag::Sub(i));
                        }
                    }
                    Val::S {
                        sym,
                        k: k.wrapping_sub(y),
                    }
                }
                _ => return abort("a counter value in an operation other than x + k or x - y"),
            };
            if let Some(d) = d {
                self.set(d, out)?;
            }
            return Ok(());
        }
        let Val::C(b) = mv else {
            return abort("unreachable: a symbolic operand");
        };
        let a = match nv {
            Some(Val::C(a)) => a,
            _ => 0,
        };
        let arith = |x: u32, y: u32, c: bool| add_with_carry(x, y, c);
        let (r, carry, overflow) = match op {
            AluOp::And => (a & b, shift_carry, None),
            AluOp::Eor => (a ^ b, shift_carry, None),
            AluOp::Orr => (a | b, shift_carry, None),
            AluOp::Orn => (a | !b, shift_carry, None),
            AluOp::Bic => (a & !b, shift_carry, None),
            AluOp::Mov => (b, shift_carry, None),
            AluOp::Mvn => (!b, shift_carry, None),
            AluOp::Mul => (a.wrapping_mul(b), None, None),
            AluOp::Add => {
                let (r, c, v) = arith(a, b, false);
                (r, Some(c), Some(v))
            }
            AluOp::Sub => {
                let (r, c, v) = arith(a, !b, true);
                (r, Some(c), Some(v))
            }
            AluOp::Rsb => {
                let (r, c, v) = arith(!a, b, true);
                (r, Some(c), Some(v))
            }
            AluOp::Adc => {
                let cin = self.known_flag(2)?;
                let (r, c, v) = arith(a, b, cin);
                (r, Some(c), Some(v))
            }
            AluOp::Sbc => {
                let cin = self.known_flag(2)?;
                let (r, c, v) = arith(a, !b, cin);
                (r, Some(c), Some(v))
            }
        };
        if s {
            self.set_flag(0, Flag::C(r >> 31 != 0));
            self.set_flag(1, Flag::C(r == 0));
            if let Some(c) = carry {
                self.set_flag(2, Flag::C(c));
            }
            if let Some(v) = overflow {
                self.set_flag(3, Flag::C(v));
            }
        }
        if let Some(d) = d {
            self.set(d, Val::C(r))?;
        }
        Ok(())
    }

    /// Execute `op` at `pc` in block `blk`; returns the branch target if it branches.
    fn step(&mut self, op: Op, pc: u32, len: u8, blk: usize) -> Res<Option<u32>> {
        // Inside an IT block: the instruction runs only if its condition holds, and the
        // 16-bit ones do not set flags.
        let in_it = self.it & 0xF != 0;
        if in_it {
            let cond = self.it >> 4;
            // Advance ITSTATE.
            self.it = if self.it & 7 == 0 {
                0
            } else {
                (self.it & 0xE0) | ((self.it << 1) & 0x1F)
            };
            if matches!(op, Op::It { .. } | Op::Cbz { .. }) {
                return abort("IT or CBZ inside an IT block");
            }
            if !self.cond(cond)? {
                return Ok(None);
            }
        }
        match op {
            Op::Nop => {}
            Op::It { first, mask } => {
                if first == 15 || (first == 14 && mask.count_ones() != 1) {
                    return abort("an undefined IT");
                }
                self.it = first << 4 | mask;
            }
            Op::Alu { op, d, n, m, s } => {
                // 16-bit instructions that set flags outside an IT block do not inside
                // one; CMP/CMN/TST always do (no destination).
                let s = s && !(in_it && len == 2 && d.is_some());
                self.alu(op, d, n, m, s, pc)?;
            }
            Op::Ext {
                d,
                m,
                rot,
                bits,
                signed,
            } => {
                let v = self.known(m, pc)?.rotate_right(u32::from(rot));
                let v = if bits == 8 { v & 0xFF } else { v & 0xFFFF };
                let v = if signed { sext(v, u32::from(bits)) } else { v };
                self.set(d, Val::C(v))?;
            }
            Op::Bfx {
                d,
                n,
                lsb,
                width,
                signed,
            } => {
                let v = self.known(n, pc)?;
                let mask = if width >= 32 {
                    u32::MAX
                } else {
                    (1u32 << width) - 1
                };
                let x = (v >> lsb) & mask;
                let x = if signed { sext(x, u32::from(width)) } else { x };
                self.set(d, Val::C(x))?;
            }
            Op::Mov16 { d, imm, top } => {
                let v = if top {
                    let old = self.known(d, pc)?;
                    (old & 0xFFFF) | u32::from(imm) << 16
                } else {
                    u32::from(imm)
                };
                self.set(d, Val::C(v))?;
            }
            Op::Load {
                t,
                n,
                off,
                size,
                signed,
            } => {
                let (addr, wb) = self.address(n, off, pc)?;
                let v = match self.env.load(addr, size, blk)? {
                    Loaded::Val(v) => {
                        let v = match size {
                            1 => v & 0xFF,
                            2 => v & 0xFFFF,
                            _ => v,
                        };
                        Val::C(if signed {
                            sext(v, 8 * u32::from(size))
                        } else {
                            v
                        })
                    }
                    Loaded::Cycles(c) => {
                        if size != 4 {
                            return abort("a part of the cycle counter");
                        }
                        let sym = self.sym_vals.len() as u8;
                        self.sym_vals.push(c);
                        Val::S { sym, k: 0 }
                    }
                };
                if let Some(a) = wb {
                    self.set(n, Val::C(a))?;
                }
                self.set(t, v)?;
            }
            Op::Store { t, n, off, size } => {
                let (addr, wb) = self.address(n, off, pc)?;
                let v = self.known(t, pc)?;
                self.env.store(addr, size, v, blk)?;
                if let Some(a) = wb {
                    self.set(n, Val::C(a))?;
                }
            }
            Op::B { cond, target } => {
                if self.cond(cond)? {
                    return Ok(Some(target));
                }
            }
            Op::Cbz { n, nz, target } => {
                let v = self.known(n, pc)?;
                if (v != 0) == nz {
                    return Ok(Some(target));
                }
            }
        }
        Ok(None)
    }
}

fn eval_cond(cond: u8, n: bool, z: bool, c: bool, v: bool) -> bool {
    match cond {
        0 => z,
        1 => !z,
        2 => c,
        3 => !c,
        4 => n,
        5 => !n,
        6 => v,
        7 => !v,
        8 => c && !z,
        9 => !c || z,
        10 => n == v,
        11 => n != v,
        12 => !z && n == v,
        13 => z || n != v,
        _ => true,
    }
}

/// A translated block of the loop: its address and its instructions.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Block {
    /// Address.
    pub addr: u32,
    /// Instructions.
    pub insns: Vec<Insn>,
}

/// Execute one iteration of the loop `blocks` (in order, back to the first) from `regs`
/// (R0–R14) and `nzcv` (bits 31–28), loads and stores through `env`. `Err` when the
/// iteration leaves the loop or does something the executor does not model.
pub fn execute(blocks: &[Block], regs: [u32; 15], nzcv: u32, env: &mut dyn Env) -> Res<Outcome> {
    let mut x = Exec {
        regs: regs.map(Val::C),
        flags: [31, 30, 29, 28].map(|b| Flag::C(nzcv >> b & 1 != 0)),
        subs: Vec::new(),
        sym_vals: Vec::new(),
        written: 0,
        live_in: 0,
        flags_written: 0,
        flags_live_in: 0,
        constraints: Vec::new(),
        env,
        it: 0,
    };
    let mut insns = 0u64;
    for (bi, b) in blocks.iter().enumerate() {
        let next = blocks[(bi + 1) % blocks.len()].addr;
        let mut pc_next = None;
        for (k, &(pc, len, op)) in b.insns.iter().enumerate() {
            insns += 1;
            let last = k + 1 == b.insns.len();
            let target = x.step(op, pc, len, bi)?;
            if let Some(t) = target {
                if !last {
                    return abort("a branch inside a block");
                }
                pc_next = Some(t);
            } else if last {
                pc_next = Some(pc + u32::from(len));
            }
        }
        if pc_next != Some(next) {
            return abort("the iteration leaves the loop");
        }
    }
    if x.it != 0 {
        return abort("an IT block across the loop's end");
    }
    Ok(Outcome {
        regs: x.regs,
        flags: x.flags,
        subs: x.subs,
        sym_vals: x.sym_vals,
        live_in: x.live_in,
        flags_live_in: x.flags_live_in,
        constraints: x.constraints,
        insns,
    })
}

/// Whether `o`, an iteration that started from `regs`/`nzcv`, leaves every register and
/// flag it read before writing as it found it: then the next iteration starts from what
/// it started from, as far as anything it reads goes.
pub fn is_fixpoint(o: &Outcome, regs: &[u32; 15], nzcv: u32) -> bool {
    for (r, (&out, &inp)) in o.regs.iter().zip(regs).enumerate() {
        if o.live_in & (1 << r) != 0 && out != Val::C(inp) {
            return false;
        }
    }
    for i in 0..4 {
        if o.flags_live_in & (8 >> i) != 0 && o.flags[i] != Flag::C(nzcv >> (31 - i) & 1 != 0) {
            return false;
        }
    }
    true
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The erase's loop of `board/flash.rs` as the image has it (at 0x2000_6040).
    const ERASE_LOOP: [u8; 18] = [
        0xCE, 0xF8, 0x00, 0x40, // str.w r4, [lr]
        0x08, 0x68, // ldr r0, [r1]
        0xC5, 0x03, // lsls r5, r0, #15
        0x03, 0xD5, // bpl done
        0x15, 0x68, // ldr r5, [r2]
        0xED, 0x1A, // subs r5, r5, r3
        0x65, 0x45, // cmp r5, r12
        0xF6, 0xD9, // bls loop
    ];

    struct Board {
        sr: u32,
        cyc: u32,
        stores: Vec<(u32, u32)>,
    }

    impl Env for Board {
        fn load(&mut self, addr: u32, _size: u8, _blk: usize) -> Res<Loaded> {
            match addr {
                0x4002_3C0C => Ok(Loaded::Val(self.sr)),
                0xE000_1004 => Ok(Loaded::Cycles(self.cyc)),
                _ => abort("elsewhere"),
            }
        }
        fn store(&mut self, addr: u32, _size: u8, value: u32, _blk: usize) -> Res<()> {
            self.stores.push((addr, value));
            Ok(())
        }
    }

    fn erase_blocks() -> Vec<Block> {
        let at = 0x2000_6040;
        let all = decode_block(&ERASE_LOOP, at).unwrap();
        // The engine's blocks end at each branch.
        let first: Vec<Insn> = all[..4].to_vec();
        let second: Vec<Insn> = all[4..].to_vec();
        vec![
            Block {
                addr: at,
                insns: first,
            },
            Block {
                addr: at + 10,
                insns: second,
            },
        ]
    }

    fn erase_regs(start: u32) -> [u32; 15] {
        let mut r = [0u32; 15];
        r[1] = 0x4002_3C0C;
        r[2] = 0xE000_1004;
        r[3] = start;
        r[4] = 0xAAAA;
        r[12] = 0x1E0A_6E00;
        r[14] = 0x4000_3000;
        r[5] = 12345; // dead
        r
    }

    #[test]
    fn the_erase_loop_is_a_fixpoint_whose_timeout_is_an_interval_of_the_counter() {
        let blocks = erase_blocks();
        assert!(matches!(
            blocks[1].insns[3].2,
            Op::B {
                cond: 9,
                target: 0x2000_6040
            }
        ));
        let regs = erase_regs(1_000);
        let mut b = Board {
            sr: 1 << 16,
            cyc: 5_000,
            stores: Vec::new(),
        };
        let o = execute(&blocks, regs, 0, &mut b).unwrap();
        assert_eq!(b.stores, vec![(0x4000_3000, 0xAAAA)]);
        assert_eq!(o.insns, 8);
        assert!(is_fixpoint(&o, &regs, 0), "{o:?}");
        // r5 and the flags are dead at the head: written before read.
        assert_eq!(o.live_in & (1 << 5), 0);
        assert_eq!(o.flags_live_in, 0);
        assert_eq!(
            o.regs[5],
            Val::S {
                sym: 0,
                k: 0u32.wrapping_sub(1_000)
            }
        );
        // The path holds while cyccnt - 1000 <= 0x1E0A6E00.
        assert_eq!(o.constraints.len(), 1);
        let c = o.constraints[0];
        assert!(c.holds.contains(1_000 + 0x1E0A_6E00));
        assert!(!c.holds.contains(1_001 + 0x1E0A_6E00));
        assert_eq!(
            c.holds.exit_distance(5_000),
            Some(0x1E0A_6E00 + 1_001 - 5_000)
        );
        // Concretely at a counter value: the flags of cmp r5, r12.
        let (r, nzcv) = o.concrete(&[5_000]).unwrap();
        assert_eq!(r[5], 4_000);
        assert_eq!(nzcv >> 28, 0b1000, "N (negative), no carry");
    }

    #[test]
    fn a_busy_flag_clear_leaves_the_loop_and_the_timeout_too() {
        let blocks = erase_blocks();
        let regs = erase_regs(0);
        let mut b = Board {
            sr: 0,
            cyc: 10,
            stores: Vec::new(),
        };
        assert!(execute(&blocks, regs, 0, &mut b).is_err(), "BSY clear: out");
        let mut b = Board {
            sr: 1 << 16,
            cyc: 0x1E0A_6E01,
            stores: Vec::new(),
        };
        assert!(execute(&blocks, regs, 0, &mut b).is_err(), "timed out");
    }

    #[test]
    fn intervals_of_every_condition_match_the_flags() {
        for &(k, y) in &[
            (0u32, 0u32),
            (5, 7),
            (0x8000_0000, 3),
            (1, 0xFFFF_FFFF),
            (9, 0x7FFF_FFFF),
        ] {
            for cond in [0u8, 1, 2, 3, 4, 5, 8, 9, 10, 11, 12, 13] {
                let iv = Interval::of_sub(cond, k, y).unwrap();
                for c in [
                    0u32,
                    1,
                    2,
                    6,
                    7,
                    8,
                    0x7FFF_FFFE,
                    0x7FFF_FFFF,
                    0x8000_0000,
                    0x8000_0001,
                    0xFFFF_FFF8,
                    0xFFFF_FFFE,
                    0xFFFF_FFFF,
                ]
                .into_iter()
                .chain([
                    y,
                    y.wrapping_sub(k),
                    y.wrapping_sub(k).wrapping_add(1),
                    y.wrapping_sub(k).wrapping_sub(1),
                ]) {
                    let [n, z, cf, v] = sub_flags(c.wrapping_add(k), y);
                    assert_eq!(
                        iv.contains(c),
                        eval_cond(cond, n, z, cf, v),
                        "cond {cond} k {k:#x} y {y:#x} c {c:#x}"
                    );
                }
            }
        }
    }

    #[test]
    fn an_rcc_ready_poll_is_a_fixpoint_with_no_counter() {
        // ldr r0, [r1]; lsls r0, r0, #14; bpl loop (HSERDY, bit 17).
        let code = [0x08, 0x68, 0x80, 0x03, 0xFC, 0xD5];
        let insns = decode_block(&code, 0x0800_1000).unwrap();
        let blocks = [Block {
            addr: 0x0800_1000,
            insns,
        }];
        struct Rcc(u32);
        impl Env for Rcc {
            fn load(&mut self, addr: u32, _: u8, _: usize) -> Res<Loaded> {
                assert_eq!(addr, 0x4002_3800);
                Ok(Loaded::Val(self.0))
            }
            fn store(&mut self, _: u32, _: u8, _: u32, _: usize) -> Res<()> {
                abort("no")
            }
        }
        let mut regs = [0u32; 15];
        regs[1] = 0x4002_3800;
        let o = execute(&blocks, regs, 0, &mut Rcc(0x83)).unwrap();
        assert!(o.constraints.is_empty());
        assert!(is_fixpoint(&o, &regs, 0));
        assert_eq!(o.concrete(&[]).unwrap().0[0], 0x83 << 14);
        // Ready: the loop is left.
        assert!(execute(&blocks, regs, 0, &mut Rcc(0x83 | 1 << 17)).is_err());
    }

    #[test]
    fn a_counting_loop_is_not_a_fixpoint_and_push_is_refused() {
        // subs r0, #1; bne loop
        let code = [0x01, 0x38, 0xFD, 0xD1];
        let blocks = [Block {
            addr: 0x100,
            insns: decode_block(&code, 0x100).unwrap(),
        }];
        struct Nothing;
        impl Env for Nothing {
            fn load(&mut self, _: u32, _: u8, _: usize) -> Res<Loaded> {
                abort("no")
            }
            fn store(&mut self, _: u32, _: u8, _: u32, _: usize) -> Res<()> {
                abort("no")
            }
        }
        let mut regs = [0u32; 15];
        regs[0] = 10;
        let o = execute(&blocks, regs, 0, &mut Nothing).unwrap();
        assert!(!is_fixpoint(&o, &regs, 0));
        assert!(decode_block(&[0x80, 0xB5], 0).is_err(), "push {{r7, lr}}");
        assert!(decode_block(&[0x00, 0xF0, 0x00, 0xF8], 0).is_err(), "bl");
    }

    #[test]
    fn thirty_two_bit_forms_decode_as_the_architecture_says() {
        // movw r1, #15372; movt r1, #16386 → 0x4002_3C0C
        let code = [0x43, 0xF6, 0x0C, 0x41, 0xC4, 0xF2, 0x02, 0x01];
        let insns = decode_block(&code, 0).unwrap();
        struct Nothing;
        impl Env for Nothing {
            fn load(&mut self, _: u32, _: u8, _: usize) -> Res<Loaded> {
                abort("no")
            }
            fn store(&mut self, _: u32, _: u8, _: u32, _: usize) -> Res<()> {
                abort("no")
            }
        }
        let mut x = Exec {
            regs: [Val::C(0); 15],
            flags: [Flag::C(false); 4],
            subs: Vec::new(),
            sym_vals: Vec::new(),
            written: 0,
            live_in: 0,
            flags_written: 0,
            flags_live_in: 0,
            constraints: Vec::new(),
            env: &mut Nothing,
            it: 0,
        };
        for (pc, _, op) in insns {
            x.step(op, pc, 4, 0).unwrap();
        }
        assert_eq!(x.regs[1], Val::C(0x4002_3C0C));
        // orr r0, r0, #65536 (modified immediate).
        let ins = decode_block(&[0x40, 0xF4, 0x80, 0x30], 0).unwrap();
        assert_eq!(
            ins[0].2,
            Op::Alu {
                op: AluOp::Orr,
                d: Some(0),
                n: Some(0),
                m: Opnd::Imm(0x1_0000, Some(false)),
                s: false
            }
        );
        // b.w backwards and bls.w forwards.
        let ins = decode_block(&[0xFF, 0xF7, 0xFE, 0xBF], 0x1000).unwrap();
        assert_eq!(
            ins[0].2,
            Op::B {
                cond: 14,
                target: 0x1000
            }
        );
        let ins = decode_block(&[0x40, 0xF2, 0x02, 0x80], 0x1000).unwrap();
        assert_eq!(
            ins[0].2,
            Op::B {
                cond: 9,
                target: 0x1008
            }
        );
        // ldr.w r0, [r1, #0x30]; ldrb r0, [r1, #-4]; ldr r0, [r1, r2, lsl #2]
        let ins = decode_block(
            &[
                0xD1, 0xF8, 0x30, 0x00, 0x11, 0xF8, 0x04, 0x0C, 0x51, 0xF8, 0x22, 0x00,
            ],
            0,
        )
        .unwrap();
        assert_eq!(
            ins.iter().map(|i| i.2).collect::<Vec<_>>(),
            vec![
                Op::Load {
                    t: 0,
                    n: 1,
                    off: Off::Imm(0x30, true, false),
                    size: 4,
                    signed: false
                },
                Op::Load {
                    t: 0,
                    n: 1,
                    off: Off::Imm(-4, true, false),
                    size: 1,
                    signed: false
                },
                Op::Load {
                    t: 0,
                    n: 1,
                    off: Off::Reg(2, 2),
                    size: 4,
                    signed: false
                },
            ]
        );
    }
}
