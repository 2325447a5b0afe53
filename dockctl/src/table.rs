//! The board's reports for a person: aligned tables with units, the unit taken from the
//! field's name as the console spells it (`force_n` → N, `pos_mm` → mm,
//! `load_distance_nmm` → N·mm, `t_s` → s); and as CSV for a spreadsheet. Fields the tool
//! does not know (a later firmware may add some: the formats only grow) are shown the
//! same way.

use crate::json::J;

/// A field's label and unit from its name.
pub fn label_unit(key: &str) -> (String, &'static str) {
    const UNITS: [(&str, &str); 10] = [
        ("_nmm", "N·mm"),
        ("_mm", "mm"),
        ("_um", "µm"),
        ("_n", "N"),
        ("_cycles", "cycles"),
        ("_ms", "ms"),
        ("_s", "s"),
        ("_sps", "SPS"),
        ("_pct", "%"),
        ("_bytes", "B"),
    ];
    let (stem, unit) = UNITS
        .iter()
        .find_map(|(suffix, unit)| key.strip_suffix(suffix).map(|s| (s, *unit)))
        .unwrap_or(match key {
            "stack_used" | "stack_size" => (key, "B"),
            _ => (key, ""),
        });
    let label = match stem {
        "pos" => "position".to_string(),
        "t" => "time".to_string(),
        s => s.replace('_', " "),
    };
    (label, unit)
}

/// Whether `v` is shown right-aligned (a number).
fn numeric(v: &J) -> bool {
    matches!(v, J::Num(_))
}

/// A report as a two-column table: `label  value unit`, nested objects as indented
/// groups; arrays of records follow as row tables under their name.
pub fn key_values(report: &J) -> String {
    let J::Obj(fields) = report else {
        return format!("{}\n", report.plain());
    };
    // (indent, label, value, unit, numeric)
    let mut rows: Vec<(usize, String, String, &str, bool)> = Vec::new();
    let mut tables: Vec<(String, &Vec<J>)> = Vec::new();
    for (k, v) in fields {
        match v {
            J::Obj(sub) => {
                rows.push((0, label_unit(k).0, String::new(), "", false));
                for (sk, sv) in sub {
                    let (l, u) = label_unit(sk);
                    rows.push((
                        2,
                        l,
                        sv.plain(),
                        if sv == &J::Null { "" } else { u },
                        numeric(sv),
                    ));
                }
            }
            J::Arr(items) if items.iter().all(|i| matches!(i, J::Obj(_))) => {
                tables.push((k.clone(), items));
            }
            _ => {
                let (l, u) = label_unit(k);
                rows.push((
                    0,
                    l,
                    v.plain(),
                    if v == &J::Null { "" } else { u },
                    numeric(v),
                ));
            }
        }
    }
    let lw = rows
        .iter()
        .map(|r| r.0 + r.1.chars().count())
        .max()
        .unwrap_or(0);
    let nw = rows
        .iter()
        .filter(|r| r.4)
        .map(|r| r.2.chars().count())
        .max()
        .unwrap_or(0);
    let mut out = String::new();
    for (indent, label, value, unit, num) in &rows {
        let pad = lw - indent - label.chars().count();
        out.push_str(&" ".repeat(*indent));
        out.push_str(label);
        out.push_str(&" ".repeat(pad + 2));
        if *num {
            out.push_str(&" ".repeat(nw.saturating_sub(value.chars().count())));
        }
        out.push_str(value);
        if !unit.is_empty() {
            out.push(' ');
            out.push_str(unit);
        }
        out.push('\n');
        while out.ends_with(" \n") {
            out.truncate(out.len() - 2);
            out.push('\n');
        }
    }
    for (name, items) in tables {
        out.push('\n');
        out.push_str(&format!("{} ({})\n", label_unit(&name).0, items.len()));
        out.push_str(&rows_table(items));
    }
    out
}

/// The columns of a list of records: every field name, in the order first seen.
fn columns(items: &[J]) -> Vec<String> {
    let mut cols: Vec<String> = Vec::new();
    for i in items {
        if let J::Obj(f) = i {
            for (k, _) in f {
                if !cols.contains(k) {
                    cols.push(k.clone());
                }
            }
        }
    }
    cols
}

/// Records as a table: a header (label and unit), one row each, numbers right-aligned.
pub fn rows_table(items: &[J]) -> String {
    if items.is_empty() {
        return "(none)\n".into();
    }
    let cols = columns(items);
    let heads: Vec<String> = cols
        .iter()
        .map(|c| match label_unit(c) {
            (l, "") => l,
            (l, u) => format!("{l} ({u})"),
        })
        .collect();
    let cells: Vec<Vec<(String, bool)>> = items
        .iter()
        .map(|i| {
            cols.iter()
                .map(|c| match i.get(c) {
                    Some(v) => (v.plain(), numeric(v)),
                    None => (String::new(), false),
                })
                .collect()
        })
        .collect();
    let widths: Vec<usize> = (0..cols.len())
        .map(|c| {
            cells
                .iter()
                .map(|r| r[c].0.chars().count())
                .chain([heads[c].chars().count()])
                .max()
                .unwrap_or(0)
        })
        .collect();
    // A column of numbers is right-aligned, its head too.
    let right: Vec<bool> = (0..cols.len())
        .map(|c| {
            cells
                .iter()
                .all(|r| r[c].1 || r[c].0.is_empty() || r[c].0 == "none")
        })
        .collect();
    let line = |vals: Vec<&str>| {
        let mut s = String::new();
        for (c, v) in vals.iter().enumerate() {
            if c > 0 {
                s.push_str("  ");
            }
            let pad = widths[c] - v.chars().count();
            if right[c] {
                s.push_str(&" ".repeat(pad));
                s.push_str(v);
            } else {
                s.push_str(v);
                s.push_str(&" ".repeat(pad));
            }
        }
        s.trim_end().to_string() + "\n"
    };
    let mut out = line(heads.iter().map(String::as_str).collect());
    for r in &cells {
        out.push_str(&line(r.iter().map(|(v, _)| v.as_str()).collect()));
    }
    out
}

/// One CSV field.
fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

/// A CSV value: numbers as the board wrote them, yes/no, empty for none.
fn csv_value(v: &J) -> String {
    match v {
        J::Null => String::new(),
        other => csv_field(&other.plain()),
    }
}

/// Records as CSV: a header of field names (with `header`), a line each.
pub fn rows_csv(items: &[J], header: bool) -> String {
    let cols = columns(items);
    let mut out = String::new();
    if header {
        out.push_str(
            &cols
                .iter()
                .map(|c| csv_field(c))
                .collect::<Vec<_>>()
                .join(","),
        );
        out.push('\n');
    }
    for i in items {
        let row: Vec<String> = cols
            .iter()
            .map(|c| i.get(c).map(csv_value).unwrap_or_default())
            .collect();
        out.push_str(&row.join(","));
        out.push('\n');
    }
    out
}

/// A report's own fields as one CSV row (nested objects flattened as `object.field`;
/// lists of records left out: they have their own commands' CSV). `prefix` columns
/// (e.g. the line the board was read on) come first.
pub fn flat_csv(report: &J, prefix: &[(&str, String)], header: bool) -> String {
    let mut cols: Vec<String> = prefix.iter().map(|(k, _)| k.to_string()).collect();
    let mut vals: Vec<String> = prefix.iter().map(|(_, v)| csv_field(v)).collect();
    if let J::Obj(f) = report {
        for (k, v) in f {
            match v {
                J::Obj(sub) => {
                    for (sk, sv) in sub {
                        cols.push(format!("{k}.{sk}"));
                        vals.push(csv_value(sv));
                    }
                }
                J::Arr(_) => {}
                v => {
                    cols.push(k.clone());
                    vals.push(csv_value(v));
                }
            }
        }
    }
    let mut out = String::new();
    if header {
        out.push_str(
            &cols
                .iter()
                .map(|c| csv_field(c))
                .collect::<Vec<_>>()
                .join(","),
        );
        out.push('\n');
    }
    out.push_str(&vals.join(","));
    out.push('\n');
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn units_come_from_the_names() {
        assert_eq!(label_unit("force_n"), ("force".into(), "N"));
        assert_eq!(label_unit("pos_mm"), ("position".into(), "mm"));
        assert_eq!(
            label_unit("load_distance_nmm"),
            ("load distance".into(), "N·mm")
        );
        assert_eq!(
            label_unit("remaining_cycles"),
            ("remaining".into(), "cycles")
        );
        assert_eq!(label_unit("t_s"), ("time".into(), "s"));
        assert_eq!(label_unit("stack_used"), ("stack used".into(), "B"));
        assert_eq!(label_unit("state"), ("state".into(), ""));
    }

    #[test]
    fn a_report_is_aligned_with_units_and_its_records_follow() {
        let j = J::parse(
            r#"{"active":null,"count_since_boot":2,"peak_force_n":207.173,"resets":{"power_on":1,"watchdog":0},"faults":[{"kind":"overload","cycle":3,"t_s":1.500},{"kind":"estop","cycle":12,"t_s":10.250}]}"#,
        )
        .unwrap();
        assert_eq!(
            key_values(&j),
            "active            none\n\
             count since boot        2\n\
             peak force        207.173 N\n\
             resets\n  \
               power on              1\n  \
               watchdog              0\n\
             \n\
             faults (2)\n\
             kind      cycle  time (s)\n\
             overload      3     1.500\n\
             estop        12    10.250\n"
        );
    }

    #[test]
    fn csv_keeps_the_boards_digits_and_quotes_what_needs_it() {
        let j =
            J::parse(r#"[{"cycle":1,"wear_mm":0.003018,"note":"a,b"},{"cycle":2,"wear_mm":null}]"#)
                .unwrap();
        let J::Arr(items) = j else { panic!() };
        assert_eq!(
            rows_csv(&items, true),
            "cycle,wear_mm,note\n1,0.003018,\"a,b\"\n2,,\n"
        );
        let w = J::parse(r#"{"cone":1,"serial":null,"resets":{"pin":2},"h":[{"a":1}]}"#).unwrap();
        assert_eq!(
            flat_csv(&w, &[("port", "/dev/ttyUSB0".into())], true),
            "port,cone,serial,resets.pin\n/dev/ttyUSB0,1,,2\n"
        );
    }
}
