//! Time stamps: signed nanoseconds since an arbitrary epoch (the sensor's or the dataset's).

use std::fmt;
use std::str::FromStr;

/// A point in time in integer nanoseconds. Integer so that association and ordering are exact;
/// dataset time stamps in decimal seconds are parsed digit by digit, never through `f64`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord, Hash, serde::Serialize, serde::Deserialize)]
pub struct Timestamp(pub i64);

const NS_PER_SEC: i64 = 1_000_000_000;

impl Timestamp {
    pub const ZERO: Timestamp = Timestamp(0);

    pub fn from_ns(t_ns: i64) -> Self {
        Timestamp(t_ns)
    }
    pub fn t_ns(self) -> i64 {
        self.0
    }
    /// Nearest nanosecond to `t_secs`. Prefer [`Timestamp::from_str`] for text.
    pub fn from_secs_f64(t_secs: f64) -> Self {
        Timestamp((t_secs * 1e9).round() as i64)
    }
    pub fn as_secs_f64(self) -> f64 {
        // Split to keep precision for large epochs (1.3e9 s * 1e9 ns overflows f64's mantissa).
        let secs = self.0.div_euclid(NS_PER_SEC);
        let ns = self.0.rem_euclid(NS_PER_SEC);
        secs as f64 + ns as f64 * 1e-9
    }
    /// Signed difference `self - earlier` in seconds.
    pub fn secs_since(self, earlier: Timestamp) -> f64 {
        (self.0 - earlier.0) as f64 * 1e-9
    }
    pub fn offset_ns(self, dt_ns: i64) -> Self {
        Timestamp(self.0 + dt_ns)
    }
}

/// Why a time stamp could not be parsed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("invalid time stamp {text:?}: {reason}")]
pub struct TimestampParseError {
    pub text: String,
    pub reason: &'static str,
}

impl FromStr for Timestamp {
    type Err = TimestampParseError;

    /// Parses decimal seconds (`1305031098.6659`, `-0.5`, `12`) exactly to nanoseconds;
    /// digits past the ninth decimal are rounded half away from zero.
    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let err = |reason| TimestampParseError { text: text.to_string(), reason };
        let s = text.trim();
        let (negative, body) = match s.strip_prefix('-') {
            Some(rest) => (true, rest),
            None => (false, s.strip_prefix('+').unwrap_or(s)),
        };
        if body.is_empty() {
            return Err(err("empty"));
        }
        let (int_part, frac_part) = match body.split_once('.') {
            Some((i, f)) => (i, f),
            None => (body, ""),
        };
        if int_part.is_empty() && frac_part.is_empty() {
            return Err(err("no digits"));
        }
        if !int_part.bytes().all(|b| b.is_ascii_digit()) || !frac_part.bytes().all(|b| b.is_ascii_digit()) {
            return Err(err("not a decimal number of seconds"));
        }
        let secs: i64 = if int_part.is_empty() {
            0
        } else {
            int_part.parse().map_err(|_| err("seconds out of range"))?
        };
        let mut frac_ns: i64 = 0;
        for (i, b) in frac_part.bytes().enumerate() {
            let d = (b - b'0') as i64;
            if i < 9 {
                frac_ns = frac_ns * 10 + d;
            } else {
                if i == 9 && d >= 5 {
                    frac_ns += 1;
                }
                break;
            }
        }
        for _ in frac_part.len()..9 {
            frac_ns *= 10;
        }
        let total = secs
            .checked_mul(NS_PER_SEC)
            .and_then(|v| v.checked_add(frac_ns))
            .ok_or_else(|| err("seconds out of range"))?;
        Ok(Timestamp(if negative { -total } else { total }))
    }
}

impl fmt::Display for Timestamp {
    /// Decimal seconds with nine decimals, e.g. `1305031098.665900000`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let sign = if self.0 < 0 { "-" } else { "" };
        let abs = self.0.unsigned_abs();
        write!(f, "{sign}{}.{:09}", abs / NS_PER_SEC as u64, abs % NS_PER_SEC as u64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_decimal_seconds_exactly() {
        assert_eq!("1305031098.6659".parse::<Timestamp>().unwrap().0, 1_305_031_098_665_900_000);
        assert_eq!("0.000000001".parse::<Timestamp>().unwrap().0, 1);
        assert_eq!("12".parse::<Timestamp>().unwrap().0, 12_000_000_000);
        assert_eq!("-0.5".parse::<Timestamp>().unwrap().0, -500_000_000);
        assert_eq!("1.0000000005".parse::<Timestamp>().unwrap().0, 1_000_000_001);
        assert!("1.2.3".parse::<Timestamp>().is_err());
        assert!("nan".parse::<Timestamp>().is_err());
        assert!("".parse::<Timestamp>().is_err());
    }

    #[test]
    fn display_round_trips() {
        for t in [0i64, 1, -1, 1_305_031_098_665_900_000, -1_500_000_000] {
            let ts = Timestamp(t);
            assert_eq!(ts.to_string().parse::<Timestamp>().unwrap(), ts);
        }
        assert_eq!(Timestamp(1_500_000_000).to_string(), "1.500000000");
    }
}
