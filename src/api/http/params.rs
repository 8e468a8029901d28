//! The request shapes: job parameters in the JSON `params` part (the query string of a raw
//! upload is `spec_query`'s), the query strings of the other routes, and the query-string
//! parser that names the parameter in its 400.

use crate::api::problem::{clip, Problem};
use crate::jobs::{parse_format, JobSpec};
use axum::http::Uri;
use serde::Deserialize;
use utoipa::IntoParams;
use willow::mesh::io::Format;

/// The `params` part of a multipart upload: a [`JobSpec`] in JSON, every field optional (the
/// server's defaults fill the rest), unknown fields refused. It is the shape of a job's
/// reported `params`, so those can be sent again as they are. A type error names its field
/// (`filter.k`, `region[0].sphere.radius`).
pub fn spec_from_json(text: &[u8]) -> Result<JobSpec, Problem> {
    if text.trim_ascii_start().first() != Some(&b'{') {
        return Err(bad_field(
            "params",
            "the `params` part must be a JSON object",
        ));
    }
    let mut de = serde_json::Deserializer::from_slice(text);
    let spec: JobSpec = serde_path_to_error::deserialize(&mut de).map_err(|e| {
        // The path names the field, an unknown one included (`filter.x`); a document that is
        // not a JSON object at all has none.
        let field = e.path().to_string();
        let inner = e.into_inner();
        // A JSON syntax error (a truncated document: "EOF while parsing an object") is the
        // part's, wherever the parser stood: serde_path_to_error names the segment it was
        // about to read `?`, which is no field a client can look up.
        if inner.is_syntax() || inner.is_eof() {
            return bad_field(
                "params",
                format!(
                    "the `params` part is not valid JSON: {} (line {}, column {})",
                    clip(&json_error_text(&inner)),
                    inner.line(),
                    inner.column()
                ),
            )
            .with("line", inner.line())
            .with("column", inner.column());
        }
        let reason = clip(&inner.to_string());
        let field = if field == "." || field.is_empty() || field.contains('?') {
            "params".to_string()
        } else {
            field
        };
        bad_field(&field, format!("in the `params` part: {reason}"))
    })?;
    de.end()
        .map_err(|e| bad_field("params", format!("trailing characters after the JSON: {e}")))?;
    Ok(spec)
}

/// serde_json's message without its own " at line L column C" (the caller says where).
fn json_error_text(e: &serde_json::Error) -> String {
    let text = e.to_string();
    let suffix = format!(" at line {} column {}", e.line(), e.column());
    text.strip_suffix(&suffix).unwrap_or(&text).to_string()
}

/// 400 `invalid_parameter` naming `field`, as the core's own parameter errors do.
pub(super) fn bad_field(field: &str, reason: impl std::fmt::Display) -> Problem {
    Problem::bad_request(
        "invalid_parameter",
        format!("invalid parameter `{field}`: {reason}"),
    )
    .with("field", field)
}

/// Comma-separated numbers (`0.1,-0.2`); empty text is an empty list.
pub(super) fn parse_list(field: &str, text: &str) -> Result<Vec<f64>, Problem> {
    if text.trim().is_empty() {
        return Ok(Vec::new());
    }
    text.split(',')
        .map(|t| {
            t.trim()
                .parse::<f64>()
                .map_err(|_| bad_field(field, format!("`{}` is not a number", t.trim())))
        })
        .collect()
}

#[derive(Debug, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct ListQuery {
    /// Only jobs in this state.
    pub state: Option<String>,
    /// 1..1000 (default 50).
    pub page_size: Option<usize>,
    pub page_token: Option<String>,
}

#[derive(Debug, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct FramesQuery {
    /// First step to return (default 0).
    pub from_step: Option<usize>,
    /// 1..10000 (default 100).
    pub page_size: Option<usize>,
}

#[derive(Debug, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct FormatQuery {
    /// `glb`, `gltf` or `obj`. Default: a frame is `glb`; the result is in the input's own
    /// format, as gRPC `DownloadResult` sends it (what you upload is what you get back).
    pub format: Option<String>,
}

#[derive(Debug, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct EventsQuery {
    /// First step to replay (default 0). The `Last-Event-ID` header, when sent, wins: the
    /// stream resumes after that step.
    pub from_step: Option<usize>,
}

/// The query string as `T`. Parsed here rather than by axum's `Query`, whose rejection is text
/// without the parameter's name: a type error (`?tau=abc`, `?steps=1.5`) becomes 400
/// `invalid_parameter` with `field` = the parameter, as every other parameter error does.
pub(super) fn query<T: serde::de::DeserializeOwned>(uri: &Uri) -> Result<T, Problem> {
    query_str(uri.query().unwrap_or(""))
}

/// [`query`] of the query string's text.
pub(super) fn query_str<T: serde::de::DeserializeOwned>(raw: &str) -> Result<T, Problem> {
    let de = serde_urlencoded::Deserializer::new(form_urlencoded::parse(raw.as_bytes()));
    serde_path_to_error::deserialize(de).map_err(|e| {
        let field = e.path().to_string();
        let inner = e.into_inner().to_string();
        // An unknown parameter has no path (it is not a field of `T`): name it from the message.
        let field = if field.is_empty() || field == "." || field == "?" {
            unknown_field_name(&inner).unwrap_or_default()
        } else {
            field
        };
        if field.is_empty() {
            Problem::bad_request(
                "invalid_parameter",
                format!("invalid query string: {}", clip(&inner)),
            )
        } else {
            let value = form_urlencoded::parse(raw.as_bytes())
                .find(|(k, _)| *k == field)
                .map(|(_, v)| v.into_owned());
            match (expected(&inner), value) {
                (Some(what), Some(value)) => {
                    bad_field(&field, format!("must be {what}, got `{}`", clip(&value)))
                }
                _ => bad_field(&field, clip(&inner)),
            }
        }
    })
}

/// What a query value had to be, from the message of the std parser that refused it: the
/// parsers' own words ("invalid digit found in string") name neither the value nor the type.
/// Every integer in the query strings [`query_str`] reads is a `usize`.
fn expected(message: &str) -> Option<&'static str> {
    match message {
        "invalid digit found in string"
        | "cannot parse integer from empty string"
        | "number too large to fit in target type" => Some("a non-negative integer"),
        "invalid float literal" | "cannot parse float from empty string" => Some("a number"),
        "provided string was not `true` or `false`" => Some("`true` or `false`"),
        _ => None,
    }
}

/// The name in serde's "unknown field `x`, expected …".
fn unknown_field_name(message: &str) -> Option<String> {
    let rest = message.strip_prefix("unknown field `")?;
    Some(rest.split_once('`')?.0.to_string())
}

/// The requested output format; `None` when the query names none (each route has its default).
pub(super) fn parse_out_format(q: &FormatQuery) -> Result<Option<Format>, Problem> {
    match &q.format {
        None => Ok(None),
        Some(f) => parse_format(f).map(Some).ok_or_else(|| {
            Problem::bad_request(
                "invalid_parameter",
                format!(
                    "invalid parameter `format`: expected `glb`, `gltf`, `obj`, `stl`, `ply` or `off`, got `{}`",
                    clip(f)
                ),
            )
            .with("field", "format")
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn refusal<T: std::fmt::Debug>(r: Result<T, Problem>) -> serde_json::Value {
        serde_json::to_value(r.expect_err("refused")).expect("json")
    }

    /// Issue 42: a truncated `params` part is the part's syntax error, named `params` with
    /// where it broke off, not the `?` of the segment the parser was about to read.
    #[test]
    fn a_truncated_params_part_names_params() {
        let p = refusal(spec_from_json(br#"{"steps": 3, "filter": {"sigma""#));
        assert_eq!(p["field"], "params", "{p}");
        assert_eq!(
            p["detail"],
            "invalid parameter `params`: the `params` part is not valid JSON: EOF while \
             parsing an object (line 1, column 31)"
        );
        assert_eq!(
            (p["line"].as_u64(), p["column"].as_u64()),
            (Some(1), Some(31))
        );
        // A type error still names its field.
        assert_eq!(
            refusal(spec_from_json(br#"{"steps": "x"}"#))["field"],
            "steps"
        );
    }

    /// Issue 42: a bad integer says what was expected and echoes the value.
    #[test]
    fn bad_query_integers_say_what_is_expected() {
        let p = refusal(query_str::<FramesQuery>("from_step=-1"));
        assert_eq!(p["field"], "from_step");
        assert_eq!(
            p["detail"],
            "invalid parameter `from_step`: must be a non-negative integer, got `-1`"
        );
        let p = refusal(query_str::<FramesQuery>("page_size=&from_step=2"));
        assert_eq!(
            p["detail"],
            "invalid parameter `page_size`: must be a non-negative integer, got ``"
        );
    }
}
