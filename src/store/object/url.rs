//! The object store a `--object-store` URL names (docs/design/scale-out.md,
//! section 2.4).

use std::io;
use std::sync::Arc;

use object_store::ObjectStore;
use object_store::aws::AmazonS3Builder;
use object_store::local::LocalFileSystem;
use object_store::prefix::PrefixStore;

/// Opens the store `url` names:
///
/// - `file:///path`: the folder `/path` (created if missing), for one
///   machine, a shared disk, and the tests;
/// - `s3://bucket` or `s3://bucket/prefix`: an S3 bucket configured from
///   the usual `AWS_*` environment variables (credentials, region,
///   `AWS_ENDPOINT_URL`, `AWS_ALLOW_HTTP`), its keys under `prefix/`.
///   Built here but not yet exercised against a server (design step 7
///   leaves the S3 test server for later).
///
/// Anything else is refused with an error saying what is accepted.
pub fn open_url(url: &str) -> io::Result<Arc<dyn ObjectStore>> {
    if let Some(path) = url.strip_prefix("file://") {
        if !path.starts_with('/') {
            return Err(invalid(format!("'{url}': a file:// object store needs an absolute path (file:///path)")));
        }
        std::fs::create_dir_all(path)?;
        let store = LocalFileSystem::new_with_prefix(path).map_err(|e| invalid(format!("'{url}': {e}")))?;
        return Ok(Arc::new(store));
    }
    if let Some(rest) = url.strip_prefix("s3://") {
        let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
        if bucket.is_empty() {
            return Err(invalid(format!("'{url}': no bucket (s3://bucket/prefix)")));
        }
        // reqwest is built without a default TLS provider (ring, not
        // aws-lc-rs); another caller may have installed it already.
        let _ = rustls::crypto::ring::default_provider().install_default();
        let s3 = AmazonS3Builder::from_env()
            .with_url(format!("s3://{bucket}"))
            .build()
            .map_err(|e| invalid(format!("'{url}': {e}")))?;
        let prefix = prefix.trim_matches('/');
        if prefix.is_empty() {
            return Ok(Arc::new(s3));
        }
        return Ok(Arc::new(PrefixStore::new(s3, prefix)));
    }
    Err(invalid(format!("'{url}' is not an object store URL (s3://bucket/prefix or file:///path)")))
}

fn invalid(message: String) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidInput, message)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn file_urls_open_a_folder_and_others_are_refused_with_the_reason() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("bucket");
        open_url(&format!("file://{}", root.display())).unwrap();
        assert!(root.is_dir(), "the folder is made");
        for (url, says) in [
            ("file://relative/x", "absolute path"),
            ("s3:///prefix", "no bucket"),
            ("http://example.com/x", "not an object store URL"),
            ("", "not an object store URL"),
        ] {
            let e = open_url(url).err().unwrap_or_else(|| panic!("{url} accepted"));
            assert_eq!(e.kind(), io::ErrorKind::InvalidInput, "{url}");
            assert!(e.to_string().contains(says), "{url}: {e}");
        }
    }
}
