//! Class names from an ultralytics export's metadata.
//!
//! ultralytics writes its metadata into the ONNX file's `metadata_props` as `str(value)`, so
//! `names` is a Python dict literal: `{0: 'person', 1: 'bicycle', ...}`, with double quotes
//! around a name that contains a single quote and backslash escapes as `repr` writes them.
//! This reads exactly that form (and JSON's, which is a subset once keys are quoted).

/// Parses a `names` value into the list of names by class index. Indices must be `0..n`
/// without gaps (a detector's output rows are the classes in order).
pub fn parse_names(s: &str) -> Result<Vec<String>, String> {
    let mut p = Parser {
        s: s.as_bytes(),
        i: 0,
    };
    p.ws();
    p.expect(b'{')?;
    let mut pairs: Vec<(usize, String)> = Vec::new();
    loop {
        p.ws();
        if p.eat(b'}') {
            break;
        }
        let key = p.key()?;
        p.ws();
        p.expect(b':')?;
        p.ws();
        let name = p.string()?;
        pairs.push((key, name));
        p.ws();
        if p.eat(b',') {
            continue;
        }
        p.ws();
        p.expect(b'}')?;
        break;
    }
    p.ws();
    if p.i != p.s.len() {
        return Err(format!("trailing text at byte {}", p.i));
    }
    pairs.sort_by_key(|(k, _)| *k);
    for (want, (k, _)) in pairs.iter().enumerate() {
        if *k != want {
            return Err(format!(
                "class indices are not 0..{}: {k} where {want} was expected",
                pairs.len()
            ));
        }
    }
    Ok(pairs.into_iter().map(|(_, n)| n).collect())
}

struct Parser<'a> {
    s: &'a [u8],
    i: usize,
}

impl Parser<'_> {
    fn ws(&mut self) {
        while self.i < self.s.len() && self.s[self.i].is_ascii_whitespace() {
            self.i += 1;
        }
    }

    fn eat(&mut self, c: u8) -> bool {
        if self.s.get(self.i) == Some(&c) {
            self.i += 1;
            true
        } else {
            false
        }
    }

    fn expect(&mut self, c: u8) -> Result<(), String> {
        if self.eat(c) {
            Ok(())
        } else {
            Err(format!("expected '{}' at byte {}", c as char, self.i))
        }
    }

    /// An integer key, bare (Python) or quoted (JSON).
    fn key(&mut self) -> Result<usize, String> {
        let text = if matches!(self.s.get(self.i), Some(b'"' | b'\'')) {
            self.string()?
        } else {
            let start = self.i;
            while self.i < self.s.len() && self.s[self.i].is_ascii_digit() {
                self.i += 1;
            }
            String::from_utf8_lossy(&self.s[start..self.i]).into_owned()
        };
        text.parse()
            .map_err(|_| format!("class index {text:?} is not a non-negative integer"))
    }

    /// A single- or double-quoted string with Python's escapes.
    fn string(&mut self) -> Result<String, String> {
        let Some(&q) = self.s.get(self.i).filter(|c| matches!(c, b'"' | b'\'')) else {
            return Err(format!("expected a quoted name at byte {}", self.i));
        };
        self.i += 1;
        let mut out: Vec<u8> = Vec::new();
        loop {
            let Some(&c) = self.s.get(self.i) else {
                return Err("unterminated string".into());
            };
            self.i += 1;
            if c == q {
                break;
            }
            if c != b'\\' {
                out.push(c);
                continue;
            }
            let Some(&e) = self.s.get(self.i) else {
                return Err("unterminated escape".into());
            };
            self.i += 1;
            match e {
                b'n' => out.push(b'\n'),
                b't' => out.push(b'\t'),
                b'r' => out.push(b'\r'),
                b'x' | b'u' | b'U' => {
                    let n = match e {
                        b'x' => 2,
                        b'u' => 4,
                        _ => 8,
                    };
                    let hex = self
                        .s
                        .get(self.i..self.i + n)
                        .and_then(|h| std::str::from_utf8(h).ok())
                        .and_then(|h| u32::from_str_radix(h, 16).ok())
                        .and_then(char::from_u32)
                        .ok_or_else(|| format!("bad \\{} escape at byte {}", e as char, self.i))?;
                    self.i += n;
                    let mut buf = [0u8; 4];
                    out.extend_from_slice(hex.encode_utf8(&mut buf).as_bytes());
                }
                other => out.push(other),
            }
        }
        String::from_utf8(out).map_err(|_| "a name is not UTF-8".into())
    }
}

#[cfg(test)]
mod tests {
    use super::parse_names;

    #[test]
    fn python_repr_of_ultralytics_names() {
        let n = parse_names(
            "{0: 'person', 1: 'traffic light', 2: \"driver's seat\", 3: 'a\\\\b', 4: 'caf\\xe9'}",
        )
        .unwrap();
        assert_eq!(
            n,
            ["person", "traffic light", "driver's seat", "a\\b", "café"]
        );
        assert_eq!(
            parse_names("{\"1\": \"b\", \"0\": \"a\"}").unwrap(),
            ["a", "b"]
        );
        assert_eq!(parse_names("{}").unwrap(), Vec::<String>::new());
    }

    #[test]
    fn gaps_and_garbage_are_errors() {
        assert!(parse_names("{0: 'a', 2: 'c'}").is_err());
        assert!(parse_names("{0: 'a'").is_err());
        assert!(parse_names("['a', 'b']").is_err());
        assert!(parse_names("{0: 'a'} x").is_err());
        assert!(parse_names("{-1: 'a'}").is_err());
    }
}
