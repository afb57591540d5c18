//! Parameters shared by the stages: the method [`Profile`] that selects the defaults of
//! unset parameters, and [`Amount`], a count or a percentage of a total.

/// Which defaults a stage's unset parameters take (official-release.md, Sec. 11).
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    Default,
    clap::ValueEnum,
    serde::Deserialize,
    serde::Serialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum Profile {
    /// Follow arXiv 2510.12768 where it is specific.
    #[default]
    Paper,
    /// Reproduce the official MoSca-based code release.
    Release,
}

/// A count, or a fraction of a total written with `%` (`"1000"`, `"2%"`).
#[derive(Debug, Clone, Copy, PartialEq, serde::Deserialize, serde::Serialize)]
#[serde(try_from = "String", into = "String")]
pub enum Amount {
    /// An absolute value (a count, or a length in world units).
    Value(f64),
    /// A fraction of the relevant total (stored as 0.02 for `2%`).
    Fraction(f64),
}

impl Amount {
    /// The amount given `total` (the count or length that a fraction refers to).
    pub fn of(self, total: f64) -> f64 {
        match self {
            Amount::Value(v) => v,
            Amount::Fraction(f) => f * total,
        }
    }
}

impl std::str::FromStr for Amount {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let bad =
            || format!("'{s}' is not a non-negative number or percentage (e.g. 1000, 0.2, 2%)");
        let (num, pct) = match s.trim().strip_suffix('%') {
            Some(n) => (n, true),
            None => (s.trim(), false),
        };
        let v: f64 = num.trim().parse().map_err(|_| bad())?;
        if !(v.is_finite() && v >= 0.0) {
            return Err(bad());
        }
        Ok(if pct { Amount::Fraction(v / 100.0) } else { Amount::Value(v) })
    }
}

impl std::fmt::Display for Amount {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Amount::Value(v) => write!(f, "{v}"),
            Amount::Fraction(v) => write!(f, "{}%", v * 100.0),
        }
    }
}

impl TryFrom<String> for Amount {
    type Error = String;
    fn try_from(s: String) -> Result<Self, String> {
        s.parse()
    }
}

impl From<Amount> for String {
    fn from(a: Amount) -> String {
        a.to_string()
    }
}

/// Option-value parsers that clap runs (`#[arg(value_parser = ...)]`), so that a value out
/// of range is an error naming the option instead of a silently odd result.
pub mod check {
    use super::Amount;

    fn number<T: std::str::FromStr>(s: &str) -> Result<T, String> {
        s.trim().parse().map_err(|_| format!("'{s}' is not a number"))
    }

    /// A finite number (`NaN` and infinities are rejected).
    pub fn finite(s: &str) -> Result<f64, String> {
        let v: f64 = number(s)?;
        if v.is_finite() { Ok(v) } else { Err(format!("{v} is not a finite number")) }
    }

    /// A finite number above 0 (sizes, thresholds, scales).
    pub fn positive(s: &str) -> Result<f32, String> {
        let v: f32 = number(s)?;
        if v.is_finite() && v > 0.0 {
            Ok(v)
        } else {
            Err(format!("{v} must be a finite number above 0"))
        }
    }

    /// A number in (0, 1] (a threshold on colours in [0, 1]).
    pub fn unit(s: &str) -> Result<f32, String> {
        let v = positive(s)?;
        if v <= 1.0 { Ok(v) } else { Err(format!("{v} must be in (0, 1]")) }
    }

    /// A count of at least 1.
    pub fn count(s: &str) -> Result<usize, String> {
        let v: usize = s.trim().parse().map_err(|_| format!("'{s}' is not a count"))?;
        if v >= 1 { Ok(v) } else { Err("must be at least 1".into()) }
    }

    /// A share of a total: a count above 0, or a percentage in (0%, 100%].
    pub fn share(s: &str) -> Result<Amount, String> {
        match s.parse::<Amount>()? {
            Amount::Value(v) if v > 0.0 => Ok(Amount::Value(v)),
            Amount::Fraction(f) if f > 0.0 && f <= 1.0 => Ok(Amount::Fraction(f)),
            _ => Err(format!("'{s}' must be a count above 0 or a percentage in (0%, 100%]")),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn amount_parses_counts_and_percentages() {
        assert_eq!("1000".parse::<Amount>().unwrap(), Amount::Value(1000.0));
        assert_eq!("2%".parse::<Amount>().unwrap(), Amount::Fraction(0.02));
        assert_eq!("2%".parse::<Amount>().unwrap().of(50_000.0).round(), 1000.0);
        assert!("-1".parse::<Amount>().is_err());
        assert!("x%".parse::<Amount>().is_err());
        let s: String = Amount::Fraction(0.02).into();
        assert_eq!(s.parse::<Amount>().unwrap(), Amount::Fraction(0.02));
    }

    #[test]
    fn checks_reject_out_of_range_values() {
        assert_eq!(check::share("2%").unwrap(), Amount::Fraction(0.02));
        assert!(check::share("200%").is_err() && check::share("0").is_err());
        assert!(check::unit("2").is_err() && check::unit("0").is_err());
        assert_eq!(check::unit("0.3").unwrap(), 0.3);
        assert!(check::finite("NaN").is_err() && check::finite("inf").is_err());
        assert!(check::positive("-1").is_err() && check::count("0").is_err());
    }
}
