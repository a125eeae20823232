//! A CSV clip whose columns are a mapping's sources (`POST /v1/rigs/{id}/clips?mapping=`),
//! rewritten row by row into one whose columns are the mapping's targets, which is then read
//! as any CSV clip ([`super::clip_from_csv`]). Columns that are no source (Live Link's
//! timecode and head and eye angles, say) are kept as they are; an empty source cell is not
//! sent for that row.

use crowdmorph_core::budget::Budget;

use super::ImportError;

/// One row's `(source, value)` pairs to one value per target, or why not.
pub type RowMap<'a> = dyn FnMut(&[(String, f32)], &mut [f32]) -> Result<(), String> + 'a;

/// `bytes` (a CSV clip) with its source columns (those `is_source` accepts) replaced by one
/// column per name of `targets`, each row's values given by `map` from the row's
/// `(source, value)` pairs (it fills one value per target). The output is charged to
/// `budget` before it is written, at a bound: the input, plus per row and target 16 bytes.
pub fn map_csv(
    bytes: &[u8],
    budget: &Budget,
    is_source: &dyn Fn(&str) -> bool,
    targets: &[String],
    map: &mut RowMap<'_>,
) -> Result<Vec<u8>, ImportError> {
    let bad = |m: String| ImportError::ClipSource(m);
    let rows = bytes.iter().filter(|&&b| b == b'\n').count() as u64 + 1;
    let names: u64 = targets.iter().map(|t| t.len() as u64 + 1).sum();
    let bound = bytes.len() as u64 + rows * targets.len() as u64 * 16 + names;
    budget.charge(2 * bound, || {
        format!(
            "a mapped CSV clip of {rows} rows and {} targets",
            targets.len()
        )
    })?;
    let mut reader = csv::ReaderBuilder::new()
        .has_headers(true)
        .flexible(true)
        .trim(csv::Trim::All)
        .from_reader(bytes);
    let header = reader
        .headers()
        .map_err(|e| bad(format!("CSV header: {e}")))?
        .clone();
    let source: Vec<bool> = header.iter().map(is_source).collect();
    if !source.iter().any(|&s| s) {
        return Err(bad(
            "the CSV header names no source of the mapping (GET /v1/rigs/{id}/mappings/{name} \
             lists them)"
                .into(),
        ));
    }
    let mut out = csv::Writer::from_writer(Vec::with_capacity(bound as usize));
    let kept = header
        .iter()
        .zip(&source)
        .filter(|(_, s)| !**s)
        .map(|(h, _)| h);
    let head: Vec<&str> = kept.chain(targets.iter().map(String::as_str)).collect();
    out.write_record(&head)
        .map_err(|e| bad(format!("CSV: {e}")))?;
    let mut pairs: Vec<(String, f32)> = Vec::with_capacity(header.len());
    let mut values = vec![0f32; targets.len()];
    let mut cells: Vec<String> = Vec::with_capacity(head.len());
    for (r, record) in reader.records().enumerate() {
        let row_no = r + 2;
        let record = record.map_err(|e| bad(format!("CSV row {row_no}: {e}")))?;
        pairs.clear();
        cells.clear();
        for (i, cell) in record.iter().enumerate() {
            match (source.get(i), header.get(i)) {
                (Some(true), Some(name)) => {
                    if cell.is_empty() {
                        continue;
                    }
                    let v: f32 = cell.parse().map_err(|_| {
                        bad(format!(
                            "CSV row {row_no}, column {name:?}: {cell:?} is not a number"
                        ))
                    })?;
                    pairs.push((name.to_string(), v));
                }
                _ => cells.push(cell.to_string()),
            }
        }
        map(&pairs, &mut values).map_err(|m| bad(format!("CSV row {row_no}: {m}")))?;
        cells.extend(values.iter().map(|v| v.to_string()));
        out.write_record(&cells)
            .map_err(|e| bad(format!("CSV: {e}")))?;
    }
    let written = out.into_inner().map_err(|e| bad(format!("CSV: {e}")))?;
    budget.release((2 * bound).saturating_sub(written.len() as u64));
    Ok(written)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sources_become_targets_and_the_rest_is_kept() {
        let csv = b"Timecode,A,B\n00:01,0.5,0.25\n00:02,1,\n";
        let budget = Budget::new(1 << 20, "--test", None);
        let targets = ["x".to_string(), "y".to_string()];
        let out = map_csv(
            csv,
            &budget,
            &|n| n == "A" || n == "B",
            &targets,
            &mut |pairs, values| {
                // x = 2·A, y = B (0 when not sent).
                values.fill(0.0);
                for (n, v) in pairs {
                    match n.as_str() {
                        "A" => values[0] = 2.0 * v,
                        _ => values[1] = *v,
                    }
                }
                Ok(())
            },
        )
        .expect("mapped");
        assert_eq!(
            String::from_utf8(out).expect("utf8"),
            "Timecode,x,y\n00:01,1,0.25\n00:02,2,0\n"
        );
        let err = map_csv(b"A\nnope\n", &budget, &|_| true, &targets, &mut |_, _| {
            Ok(())
        });
        assert!(matches!(err, Err(ImportError::ClipSource(m)) if m.contains("not a number")));
        let none = map_csv(b"Z\n1\n", &budget, &|_| false, &targets, &mut |_, _| Ok(()));
        assert!(none.is_err());
    }
}
