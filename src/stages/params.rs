//! Parameters shared by the stages: the method [`Profile`] that selects the defaults of
//! unset parameters, [`Amount`], a count or a percentage of a total, the option-value
//! parsers of [`check`], and [`stage_params!`](crate::stage_params), which turns one
//! declaration per parameter into everything a stage needs.
//!
//! A stage parameter is declared once: its name, help, the parser of its command-line
//! value, the paper and release values (spelled as on the command line, parsed by that
//! same parser) and, where it has one, the row of official-release.md §11 it comes from.
//! Each parameter stands in the group of its `--help` heading (a heading may open several
//! groups; clap lists the headings in the order they first appear):
//!
//! ```ignore
//! stage_params! {
//!     /// Parameters of `usplat4d uncertainty`; unset values take the profile's defaults.
//!     pub struct UncertaintyParams;
//!     /// Concrete settings (recorded in the table's provenance).
//!     pub struct UncertaintySettings;
//!     inputs {
//!         /// Model directory (gaussians.parquet + trajectories.parquet).
//!         #[arg(long, value_name = "MODEL_DIR")]
//!         model: PathBuf,
//!     }
//!     params {
//!         heading "Method" {
//!             /// Colour-error threshold η_c, in (0, 1].
//!             eta_c: f32 => f32 [check::unit] { paper "0.5", release "0.3", row "5" },
//!             /// SSIM gate threshold, 0 for off.
//!             ssim_gate: f32 => Option<f32> [check::finite32] { paper "0", release "0.01" },
//!             graph_scope: GraphScope => GraphScope { shared GRAPH_SCOPE },
//!         }
//!     }
//!     copied {
//!         heading "Method" {
//!             /// Seed of the random picks.
//!             seed: u64 [check::parsed] { default "0" },
//!         }
//!     }
//! }
//! ```
//!
//! This generates the clap/serde struct `UncertaintyParams` (the inputs, `--profile`, then
//! one `Option<CLI type>` per parameter, so that an unset one takes the profile's value; its
//! help ends in `[paper 0.5, release 0.3; official-release §11 row 5]`), the settings
//! struct `UncertaintySettings` (the profile, then one field of the settings type per
//! parameter, then the `copied` fields), `UncertaintySettings::defaults(profile)` and
//! `UncertaintyParams::resolve()`. A given value becomes a setting through [`FromGiven`]:
//! unchanged, or `0` meaning "off" (`None`) where the settings type is an `Option`. Both
//! structs serialise in declaration order with kebab-case names (the tables' provenance
//! records both). `copied` fields (e.g. a seed) have one value whatever the profile and go
//! to the settings unchanged. A parameter that several stages take with one meaning
//! (`graph-scope`) is a [`Shared`] constant, which holds its help, parser and values, and
//! each stage names it with `{ shared NAME }`, without doc lines or parser (either is a
//! compile error, so neither can silently differ from the constant's).
//!
//! A heading declared `heading "Learning rates" as lr: LearningRates { .. }` also generates
//! the struct `LearningRates`, one field per parameter under it, and the settings' method
//! `lr()` that copies them out: a stage whose code takes its settings in groups (the
//! optimiser's learning rates and density control) gets them without restating a field.
//!
//! A new stage declares its block the same way in its own `params.rs`: inputs, then one
//! line per parameter with the §11 row, then `copied`; its extra checks belong in a
//! [`check`] parser so that clap reports them by option name.

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

    /// A finite `f32` (`NaN` and infinities are rejected).
    pub fn finite32(s: &str) -> Result<f32, String> {
        let v: f32 = number(s)?;
        if v.is_finite() { Ok(v) } else { Err(format!("{v} is not a finite number")) }
    }

    /// A fraction in [0, 1].
    pub fn fraction(s: &str) -> Result<f32, String> {
        let v = finite32(s)?;
        if (0.0..=1.0).contains(&v) { Ok(v) } else { Err(format!("{v} must be in [0, 1]")) }
    }

    /// A percentile in [0, 100].
    pub fn percentile(s: &str) -> Result<f32, String> {
        let v = finite32(s)?;
        if (0.0..=100.0).contains(&v) { Ok(v) } else { Err(format!("{v} must be in [0, 100]")) }
    }

    /// A finite number at least 0.
    pub fn non_negative(s: &str) -> Result<f64, String> {
        let v = finite(s)?;
        if v >= 0.0 { Ok(v) } else { Err(format!("{v} must be a non-negative number")) }
    }

    /// A finite `f32` at least 0 (learning rates).
    pub fn non_negative32(s: &str) -> Result<f32, String> {
        let v = finite32(s)?;
        if v >= 0.0 { Ok(v) } else { Err(format!("{v} must be a non-negative number")) }
    }

    /// Three positive numbers `x,y,z`.
    pub fn triple(s: &str) -> Result<[f64; 3], String> {
        let v: Vec<f64> = s.split(',').map(number).collect::<Result<_, _>>()?;
        match v[..] {
            [x, y, z] if v.iter().all(|c| c.is_finite() && *c > 0.0) => Ok([x, y, z]),
            _ => Err(format!("'{s}': expected three positive numbers x,y,z")),
        }
    }

    /// Any value with a `FromStr` (counts, flags, and the stages' own value types).
    pub fn parsed<T: std::str::FromStr>(s: &str) -> Result<T, String>
    where
        T::Err: std::fmt::Display,
    {
        s.trim().parse().map_err(|e| format!("'{s}': {e}"))
    }

    /// One of a `clap::ValueEnum`'s spellings.
    pub fn choice<T: clap::ValueEnum>(s: &str) -> Result<T, String> {
        T::from_str(s.trim(), false).map_err(|_| {
            let names: Vec<String> = T::value_variants()
                .iter()
                .filter_map(|v| v.to_possible_value())
                .map(|v| v.get_name().to_string())
                .collect();
            format!("'{s}' is not one of {}", names.join(", "))
        })
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

/// How a given command-line value becomes a setting: unchanged, or `0` meaning "off".
pub trait FromGiven<C>: Sized {
    /// The setting for the given value `c`.
    fn from_given(c: C) -> Self;
}

impl<T> FromGiven<T> for T {
    fn from_given(c: T) -> T {
        c
    }
}

impl FromGiven<f32> for Option<f32> {
    fn from_given(c: f32) -> Self {
        (c != 0.0).then_some(c)
    }
}

impl FromGiven<f64> for Option<f64> {
    fn from_given(c: f64) -> Self {
        (c != 0.0).then_some(c)
    }
}

impl FromGiven<u32> for Option<u32> {
    fn from_given(c: u32) -> Self {
        (c != 0).then_some(c)
    }
}

impl FromGiven<usize> for Option<usize> {
    fn from_given(c: usize) -> Self {
        (c != 0).then_some(c)
    }
}

/// The setting a declared default spells (`name` for the message): a declaration error,
/// caught by every stage's profile test, hence a panic rather than a user-facing error.
pub fn declared<C, S: FromGiven<C>>(
    name: &str,
    spelled: &str,
    parse: fn(&str) -> Result<C, String>,
) -> S {
    match parse(spelled) {
        Ok(c) => S::from_given(c),
        Err(e) => panic!("the declared default of {name}, '{spelled}', does not parse: {e}"),
    }
}

/// A parameter's help: its doc lines, then `[paper X, release Y; official-release §11 row N]`.
pub fn help(doc: &[&str], paper: &str, release: &str, row: &str) -> String {
    let text: Vec<&str> = doc.iter().map(|l| l.trim()).collect();
    let row =
        if row.is_empty() { String::new() } else { format!("; official-release §11 row {row}") };
    let text = text.join(" ");
    format!("{} [paper {paper}, release {release}{row}]", text.trim_end_matches('.'))
}

/// A parameter that several stages take with one meaning and the same values, declared
/// once as a `const` beside its type and included in each stage's block with
/// `{ shared NAME }` (see the module doc).
pub struct Shared<C: 'static> {
    /// Its help, in lines (as a declaration's doc lines).
    pub doc: &'static [&'static str],
    /// The parser of its command-line value.
    pub parse: fn(&str) -> Result<C, String>,
    /// The paper profile's value, spelled as on the command line.
    pub paper: &'static str,
    /// The release profile's value, spelled as on the command line.
    pub release: &'static str,
    /// The row of official-release.md §11 it comes from (empty for none).
    pub row: &'static str,
}

/// One declaration per stage parameter generates the stage's clap arguments, its settings,
/// their defaults per profile and their resolution (see the module doc for an example).
#[macro_export]
macro_rules! stage_params {
    (
        $(#[doc = $pdoc:literal])*
        pub struct $params:ident;
        $(#[doc = $sdoc:literal])*
        pub struct $settings:ident;
        inputs {
            $(
                $(#[$iattr:meta])*
                $iname:ident: $ity:ty,
            )*
        }
        params {
            $(
                heading $heading:literal $(as $gname:ident: $gty:ident)? {
                    $(
                        $(#[doc = $doc:literal])*
                        $name:ident: $cty:ty => $sty:ty $([$parse:expr])? { $($spec:tt)* },
                    )*
                }
            )*
        }
        copied {
            $(
                heading $cheading:literal {
                    $(
                        $(#[doc = $cdoc:literal])*
                        $cname:ident: $ccty:ty [$cparse:expr] { default $cdefault:literal },
                    )*
                }
            )*
        }
    ) => {
        $(#[doc = $pdoc])*
        #[derive(Debug, Clone, clap::Args, serde::Serialize)]
        #[serde(rename_all = "kebab-case")]
        pub struct $params {
            $(
                $(#[$iattr])*
                pub $iname: $ity,
            )*
            /// Which defaults the unset parameters take.
            #[arg(long, value_enum, default_value_t = $crate::stages::params::Profile::Paper, help_heading = "Method")]
            pub profile: $crate::stages::params::Profile,
            $($(
                $(#[doc = $doc])*
                #[doc = $crate::__stage_param!(doc { $($spec)* })]
                #[arg(
                    long,
                    value_parser = {
                        let f: fn(&str) -> Result<$cty, String> =
                            $crate::__stage_param!(parse [$($parse)?] { $($spec)* });
                        f
                    },
                    help = $crate::__stage_param!(help [$($doc)*] { $($spec)* }),
                    help_heading = $heading
                )]
                pub $name: Option<$cty>,
            )*)*
            $($(
                $(#[doc = $cdoc])*
                #[arg(
                    long,
                    value_parser = { let f: fn(&str) -> Result<$ccty, String> = $cparse; f },
                    default_value = $cdefault,
                    help_heading = $cheading
                )]
                pub $cname: $ccty,
            )*)*
        }

        $(#[doc = $sdoc])*
        #[derive(Debug, Clone, PartialEq, serde::Serialize)]
        #[serde(rename_all = "kebab-case")]
        pub struct $settings {
            /// The profile the defaults came from.
            pub profile: $crate::stages::params::Profile,
            $($(
                $(#[doc = $doc])*
                #[doc = $crate::__stage_param!(doc { $($spec)* })]
                pub $name: $sty,
            )*)*
            $($(
                $(#[doc = $cdoc])*
                pub $cname: $ccty,
            )*)*
        }

        impl $settings {
            /// The defaults of `profile` (the declared paper or release values; `copied`
            /// fields their one default).
            pub fn defaults(profile: $crate::stages::params::Profile) -> Self {
                let paper = profile == $crate::stages::params::Profile::Paper;
                $settings {
                    profile,
                    $($(
                        $name: $crate::stages::params::declared::<$cty, $sty>(
                            stringify!($name),
                            $crate::__stage_param!(value paper { $($spec)* }),
                            $crate::__stage_param!(parse [$($parse)?] { $($spec)* }),
                        ),
                    )*)*
                    $($(
                        $cname: $crate::stages::params::declared::<$ccty, $ccty>(
                            stringify!($cname),
                            $cdefault,
                            $cparse,
                        ),
                    )*)*
                }
            }
        }

        $(
            $crate::__stage_param_group!($settings $heading [$($gname $gty)?] {
                $( [$($doc)*] $name: $sty { $($spec)* } ),*
            });
        )*

        impl $params {
            /// The profile's defaults with the given values applied.
            pub fn resolve(&self) -> anyhow::Result<$settings> {
                let d = $settings::defaults(self.profile);
                Ok($settings {
                    profile: self.profile,
                    $($(
                        $name: match &self.$name {
                            Some(v) => $crate::stages::params::FromGiven::from_given(v.clone()),
                            None => d.$name,
                        },
                    )*)*
                    $($(
                        $cname: self.$cname.clone(),
                    )*)*
                })
            }
        }
    };
}

/// The parts of one [`stage_params!`](crate::stage_params) parameter, from its own
/// `{ paper "..", release ".." [, row ".."] }` or from a [`Shared`] declaration. `doc` is a
/// field's extra doc line: a link to the [`Shared`] constant, empty for the others (clap reads
/// only literal doc lines, so it does not change the help).
#[doc(hidden)]
#[macro_export]
macro_rules! __stage_param {
    (doc { shared $decl:path }) => {
        concat!("Declared once for the stages that take it: [`", stringify!($decl), "`].")
    };
    (doc { $($spec:tt)* }) => {
        ""
    };
    (help [$($doc:literal)*] { paper $paper:literal, release $release:literal $(, row $row:literal)? $(,)? }) => {
        $crate::stages::params::help(&[$($doc),*], $paper, $release, concat!("" $(, $row)?))
    };
    (help [] { shared $decl:path }) => {
        $crate::stages::params::help($decl.doc, $decl.paper, $decl.release, $decl.row)
    };
    (value $paper_profile:ident { paper $paper:literal, release $release:literal $(, row $row:literal)? $(,)? }) => {
        if $paper_profile { $paper } else { $release }
    };
    (value $paper_profile:ident { shared $decl:path }) => {
        if $paper_profile { $decl.paper } else { $decl.release }
    };
    (parse [$parse:expr] { shared $decl:path }) => {
        compile_error!(concat!("a shared parameter takes its parser from ", stringify!($decl)))
    };
    (parse [$parse:expr] { $($spec:tt)* }) => {
        $parse
    };
    (parse [] { shared $decl:path }) => {
        $decl.parse
    };
}

/// The struct of a [`stage_params!`](crate::stage_params) heading declared
/// `heading "..." as NAME: TYPE`: one field per parameter under it (same name, type and doc
/// as the settings' field) and the settings' method `NAME()` that copies them out; nothing for
/// a heading without a group.
#[doc(hidden)]
#[macro_export]
macro_rules! __stage_param_group {
    ($settings:ident $heading:literal [] { $($params:tt)* }) => {};
    ($settings:ident $heading:literal [$gname:ident $gty:ident] {
        $( [$($doc:literal)*] $name:ident: $sty:ty { $($spec:tt)* } ),*
    }) => {
        #[doc = concat!("The parameters under \"", $heading, "\" ([`", stringify!($settings),
            "::", stringify!($gname), "`]).")]
        #[derive(Debug, Clone, PartialEq, serde::Serialize)]
        #[serde(rename_all = "kebab-case")]
        pub struct $gty {
            $(
                $(#[doc = $doc])*
                #[doc = $crate::__stage_param!(doc { $($spec)* })]
                pub $name: $sty,
            )*
        }

        impl $settings {
            #[doc = concat!("The parameters under \"", $heading, "\", grouped.")]
            pub fn $gname(&self) -> $gty {
                $gty { $($name: self.$name.clone(),)* }
            }
        }
    };
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
