//! Command-line values the tools parse.

/// Parses `X,Y,Z` into three positive dimensions.
///
/// # Errors
/// Not three positive integers.
pub fn parse_dims(s: &str) -> Result<[u32; 3], String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let d: Vec<u32> = parts
        .iter()
        .map(|p| {
            p.parse::<u32>()
                .map_err(|_| format!("{p:?} is not a valid number"))
        })
        .collect::<Result<_, _>>()?;
    match d[..] {
        [x, y, z] if x > 0 && y > 0 && z > 0 => Ok([x, y, z]),
        [_, _, _] => Err(format!("dimensions must be positive, got {s:?}")),
        _ => Err(format!("expected three comma-separated values, got {s:?}")),
    }
}
