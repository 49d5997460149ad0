//! An HTTP answer as a test sees it, whichever way it was fetched (in-process `oneshot`, or a
//! client against the real binary).

use serde_json::Value;

#[derive(Debug, Clone)]
pub struct Resp {
    pub status: u16,
    pub headers: Vec<(String, String)>,
    pub body: Vec<u8>,
}

impl Resp {
    pub fn json(&self) -> Value {
        serde_json::from_slice(&self.body).unwrap_or_else(|e| {
            panic!(
                "status {}: body is not JSON ({e}): {}",
                self.status,
                String::from_utf8_lossy(&self.body)
            )
        })
    }

    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(k, _)| k.eq_ignore_ascii_case(name))
            .map(|(_, v)| v.as_str())
    }

    /// Asserts an error response: the status and the `{"error", "kind"}` shape.
    pub fn expect_error(&self, status: u16, kind: &str) {
        let v = self.json();
        assert_eq!(self.status, status, "body: {v}");
        assert_eq!(v["kind"], kind, "body: {v}");
        assert!(
            v["error"].as_str().is_some_and(|s| !s.is_empty()),
            "body: {v}"
        );
    }
}
