//! The object store a `--object-store` URL names (docs/design/scale-out.md,
//! section 2.4).

use std::io;
use std::sync::Arc;

use object_store::ObjectStore;
use object_store::local::LocalFileSystem;
use object_store::path::Path as Key;
use object_store::prefix::PrefixStore;

use super::s3::{S3Options, open_bucket};

/// Opens the store `url` names:
///
/// - `file:///path`: the folder `/path` (created if missing), for one
///   machine, a shared disk, and the tests;
/// - `s3://bucket` or `s3://bucket/prefix`: an S3 bucket configured from
///   the usual `AWS_*` environment variables with `s3` over them (see
///   [`super::s3`]), its keys under `prefix/`.
///
/// Anything else is refused with an error saying what is accepted, as are
/// a bad bucket name, a prefix that is not a key (`a//b`, `..`) and bad S3
/// settings.
pub fn open_url(url: &str, s3: &S3Options) -> io::Result<Arc<dyn ObjectStore>> {
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
        let prefix = prefix.trim_end_matches('/');
        let prefix = Key::parse(prefix)
            .map_err(|e| invalid(format!("'{url}': the prefix '{prefix}' is not an object key prefix: {e}")))?;
        let store = open_bucket(url, bucket, s3)?;
        if prefix.as_ref().is_empty() {
            return Ok(Arc::new(store));
        }
        return Ok(Arc::new(PrefixStore::new(store, prefix)));
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
        open_url(&format!("file://{}", root.display()), &S3Options::default()).unwrap();
        assert!(root.is_dir(), "the folder is made");
        for (url, says) in [
            ("file://relative/x", "absolute path"),
            ("s3:///prefix", "no bucket"),
            ("s3://Bucket/prefix", "'Bucket' is not a bucket name"),
            ("s3://bucket/a//b", "the prefix 'a//b' is not an object key prefix"),
            ("s3://bucket/a/../b", "the prefix 'a/../b' is not an object key prefix"),
            ("http://example.com/x", "not an object store URL"),
            ("", "not an object store URL"),
        ] {
            let e = open_url(url, &S3Options::default()).err().unwrap_or_else(|| panic!("{url} accepted"));
            assert_eq!(e.kind(), io::ErrorKind::InvalidInput, "{url}");
            assert!(e.to_string().contains(says), "{url}: {e}");
        }
    }
}
