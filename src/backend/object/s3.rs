//! Where an `s3://` object store's settings come from, in one place
//! (docs/design/scale-out.md, section 2.4).
//!
//! The base is the usual AWS environment, read when the store is opened
//! (`object_store`'s `AmazonS3Builder::from_env`): `AWS_ACCESS_KEY_ID`,
//! `AWS_SECRET_ACCESS_KEY`, `AWS_SESSION_TOKEN`, `AWS_REGION` (or
//! `AWS_DEFAULT_REGION`; `us-east-1` when neither is set),
//! `AWS_ENDPOINT_URL` (or `AWS_ENDPOINT`; AWS itself when neither is set)
//! and `AWS_ALLOW_HTTP`, and the web-identity and container-credential
//! variables, so IAM roles keep working. [`S3Options`] overrides some of
//! them: `serve`'s `--s3-endpoint` and `--s3-region`, and callers that
//! cannot change their process's environment (the tests, which run in
//! parallel in one process).
//!
//! What is wrong is said before the first request: a bucket name S3 would
//! refuse, a prefix that is not a key, an endpoint that is not an http(s)
//! URL, a plain-HTTP endpoint without `AWS_ALLOW_HTTP=true`, a key id
//! without its secret (or the reverse).

use std::fmt;
use std::io;

use object_store::ClientConfigKey;
use object_store::aws::{AmazonS3, AmazonS3Builder, AmazonS3ConfigKey};

/// Settings that override the AWS environment for an `s3://` store
/// (`None`: the environment's, see the module comment).
#[derive(Clone, Default, PartialEq, Eq)]
pub struct S3Options {
    /// The server's URL, `http(s)://host:port` (`--s3-endpoint`; else
    /// `AWS_ENDPOINT_URL`).
    pub endpoint: Option<String>,
    /// The region requests are signed for (`--s3-region`; else
    /// `AWS_REGION`).
    pub region: Option<String>,
    /// Whether a plain-HTTP endpoint is allowed (else `AWS_ALLOW_HTTP`).
    pub allow_http: Option<bool>,
    /// A fixed key pair (else the environment's credentials).
    pub keys: Option<S3Keys>,
}

/// An S3 access key id and its secret.
#[derive(Clone, PartialEq, Eq)]
pub struct S3Keys {
    pub access_key_id: String,
    pub secret_access_key: String,
}

impl fmt::Debug for S3Keys {
    /// The key id, never the secret.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("S3Keys").field("access_key_id", &self.access_key_id).finish_non_exhaustive()
    }
}

impl fmt::Debug for S3Options {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("S3Options")
            .field("endpoint", &self.endpoint)
            .field("region", &self.region)
            .field("allow_http", &self.allow_http)
            .field("keys", &self.keys)
            .finish()
    }
}

/// The S3 store of bucket `bucket`: the AWS environment, then `options`
/// over it, checked. `url` is what the user gave, for the errors.
pub fn open_bucket(url: &str, bucket: &str, options: &S3Options) -> io::Result<AmazonS3> {
    check_bucket(bucket).map_err(|why| invalid(format!("'{url}': {why}")))?;
    let mut builder = AmazonS3Builder::from_env().with_url(format!("s3://{bucket}"));
    if let Some(endpoint) = &options.endpoint {
        builder = builder.with_endpoint(endpoint);
    }
    if let Some(region) = &options.region {
        builder = builder.with_region(region);
    }
    if let Some(allow) = options.allow_http {
        builder = builder.with_allow_http(allow);
    }
    if let Some(keys) = &options.keys {
        builder = builder.with_access_key_id(&keys.access_key_id).with_secret_access_key(&keys.secret_access_key);
    }
    let allow_http = builder
        .get_config_value(&AmazonS3ConfigKey::Client(ClientConfigKey::AllowHttp))
        .is_some_and(|v| v.eq_ignore_ascii_case("true"));
    if let Some(endpoint) = builder.get_config_value(&AmazonS3ConfigKey::Endpoint) {
        check_endpoint(&endpoint, allow_http).map_err(|why| invalid(format!("'{url}': {why}")))?;
    }
    // reqwest is built without a default TLS provider (ring, not
    // aws-lc-rs); another caller may have installed it already.
    let _ = rustls::crypto::ring::default_provider().install_default();
    builder.build().map_err(|e| invalid(format!("'{url}': {e}")))
}

/// A bucket name S3 accepts: 3 to 63 lowercase letters, digits, `-` and
/// `.`, beginning and ending with a letter or digit.
fn check_bucket(bucket: &str) -> Result<(), String> {
    let allowed = |c: char| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-' || c == '.';
    let edge = |c: Option<char>| c.is_some_and(|c| c.is_ascii_lowercase() || c.is_ascii_digit());
    if bucket.is_empty() {
        return Err("no bucket (s3://bucket/prefix)".into());
    }
    if !(3..=63).contains(&bucket.len())
        || !bucket.chars().all(allowed)
        || !edge(bucket.chars().next())
        || !edge(bucket.chars().last())
    {
        return Err(format!(
            "'{bucket}' is not a bucket name (3 to 63 lowercase letters, digits, '-' and '.', beginning and ending \
             with a letter or digit)"
        ));
    }
    Ok(())
}

/// An endpoint is an `http://` or `https://` URL; plain HTTP only when
/// allowed.
fn check_endpoint(endpoint: &str, allow_http: bool) -> Result<(), String> {
    let rest = if let Some(rest) = endpoint.strip_prefix("https://") {
        rest
    } else if let Some(rest) = endpoint.strip_prefix("http://") {
        if !allow_http {
            return Err(format!(
                "the endpoint {endpoint} is plain HTTP: set AWS_ALLOW_HTTP=true to allow it (or use https://)"
            ));
        }
        rest
    } else {
        return Err(format!("the endpoint '{endpoint}' is not an http:// or https:// URL (AWS_ENDPOINT_URL)"));
    };
    if rest.is_empty() || rest.starts_with('/') {
        return Err(format!("the endpoint '{endpoint}' names no host (AWS_ENDPOINT_URL)"));
    }
    Ok(())
}

fn invalid(message: String) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidInput, message)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn options(endpoint: &str, allow_http: bool) -> S3Options {
        S3Options {
            endpoint: Some(endpoint.into()),
            region: Some("test".into()),
            allow_http: Some(allow_http),
            keys: Some(S3Keys { access_key_id: "id".into(), secret_access_key: "hidden-secret".into() }),
        }
    }

    #[test]
    fn good_settings_build_a_store() {
        open_bucket("s3://radiance-test/x", "radiance-test", &options("http://127.0.0.1:9000", true)).unwrap();
        open_bucket("s3://a.b-c/x", "a.b-c", &options("https://s3.example.com", false)).unwrap();
    }

    #[test]
    fn bad_buckets_and_endpoints_are_refused_with_the_reason() {
        for (bucket, endpoint, allow, says) in [
            ("", "https://h", false, "no bucket"),
            ("ab", "https://h", false, "'ab' is not a bucket name"),
            ("My_Bucket", "https://h", false, "'My_Bucket' is not a bucket name"),
            ("-abc", "https://h", false, "is not a bucket name"),
            ("bucket", "http://127.0.0.1:9000", false, "plain HTTP: set AWS_ALLOW_HTTP=true"),
            ("bucket", "127.0.0.1:9000", true, "not an http:// or https:// URL"),
            ("bucket", "https://", true, "names no host"),
        ] {
            let url = format!("s3://{bucket}/p");
            let e = open_bucket(&url, bucket, &options(endpoint, allow))
                .err()
                .unwrap_or_else(|| panic!("{url} {endpoint}"));
            assert_eq!(e.kind(), io::ErrorKind::InvalidInput, "{e}");
            assert!(e.to_string().contains(says), "{bucket} {endpoint}: {e}");
            assert!(e.to_string().starts_with(&format!("'{url}': ")), "{e}");
        }
    }

    #[test]
    fn debug_output_hides_the_secret() {
        let shown = format!("{:?}", options("https://h", false));
        assert!(shown.contains("\"id\"") && !shown.contains("hidden-secret"), "{shown}");
    }
}
