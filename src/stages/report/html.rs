//! The pieces of the self-contained HTML page: escaping, tables, and images embedded as
//! `data:` URIs (PNG) or inline SVG, so the report is one file that opens anywhere.

use base64::Engine;

use crate::formats::png::Image;

/// `s` with the five HTML-special characters escaped.
pub fn escape(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

/// A table with a header row; every cell is escaped.
pub fn table(header: &[String], rows: &[Vec<String>]) -> String {
    let mut s = String::from("<table>\n<tr>");
    for h in header {
        s.push_str(&format!("<th>{}</th>", escape(h)));
    }
    s.push_str("</tr>\n");
    for r in rows {
        s.push_str("<tr>");
        for c in r {
            s.push_str(&format!("<td>{}</td>", escape(c)));
        }
        s.push_str("</tr>\n");
    }
    s.push_str("</table>\n");
    s
}

/// PNG bytes of an 8-bit image (grey, RGB or RGBA by its channel count).
pub fn png_bytes(img: &Image) -> anyhow::Result<Vec<u8>> {
    use image::ImageEncoder;
    let color = match img.channels {
        1 => image::ExtendedColorType::L8,
        3 => image::ExtendedColorType::Rgb8,
        4 => image::ExtendedColorType::Rgba8,
        c => anyhow::bail!("cannot encode an image of {c} channels as PNG"),
    };
    let mut bytes = Vec::new();
    image::codecs::png::PngEncoder::new(&mut bytes).write_image(
        &img.to_u8(),
        img.width as u32,
        img.height as u32,
        color,
    )?;
    Ok(bytes)
}

/// Smallest displayed width of an image, CSS pixels; smaller images are shown enlarged by
/// a whole factor (pixelated, so no detail is invented).
const MIN_DISPLAY_WIDTH: usize = 192;

/// An `<img>` element holding `img` as an embedded PNG.
pub fn img(img: &Image, alt: &str) -> anyhow::Result<String> {
    let b64 = base64::engine::general_purpose::STANDARD.encode(png_bytes(img)?);
    let zoom = MIN_DISPLAY_WIDTH.div_ceil(img.width.max(1)).max(1);
    Ok(format!(
        "<img alt=\"{}\" width=\"{}\" src=\"data:image/png;base64,{b64}\">",
        escape(alt),
        img.width * zoom
    ))
}

/// A captioned figure around `body` (an `<img>` or an inline `<svg>`).
pub fn figure(body: &str, caption: &str) -> String {
    format!("<figure>{body}<figcaption>{}</figcaption></figure>\n", escape(caption))
}

/// The whole page: a title, a table of contents and the sections `(id, heading, body)`.
pub fn page(title: &str, sections: &[(String, String, String)]) -> String {
    let mut s = format!(
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n\
         <title>{t}</title>\n<style>{STYLE}</style>\n</head>\n<body>\n<h1>{t}</h1>\n<nav><ol>\n",
        t = escape(title)
    );
    for (id, heading, _) in sections {
        s.push_str(&format!("<li><a href=\"#{id}\">{}</a></li>\n", escape(heading)));
    }
    s.push_str("</ol></nav>\n");
    for (id, heading, body) in sections {
        s.push_str(&format!(
            "<section id=\"{id}\">\n<h2>{}</h2>\n{body}</section>\n",
            escape(heading)
        ));
    }
    s.push_str("</body>\n</html>\n");
    s
}

const STYLE: &str = "body{font-family:system-ui,sans-serif;margin:2em;max-width:1400px;color:#222}\
table{border-collapse:collapse;margin:0.5em 0 1.5em}\
td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}th{background:#f3f3f3}\
td:first-child,th:first-child{text-align:left}\
figure{display:inline-block;margin:0.5em;vertical-align:top}\
figcaption{font-size:0.85em;color:#555;text-align:center}\
img{image-rendering:pixelated;max-width:100%}\
.grid{display:grid;gap:4px;align-items:start}.grid div{font-size:0.8em;text-align:center}";

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn escapes_markup() {
        assert_eq!(
            escape("<a href=\"x\">&'</a>"),
            "&lt;a href=&quot;x&quot;&gt;&amp;&#39;&lt;/a&gt;"
        );
    }

    #[test]
    fn embedded_png_decodes_back() {
        let im =
            Image { width: 2, height: 1, channels: 3, data: vec![1.0, 0.0, 0.0, 0.0, 0.0, 1.0] };
        let back = image::load_from_memory(&png_bytes(&im).unwrap()).unwrap().to_rgb8();
        assert_eq!(back.into_raw(), vec![255, 0, 0, 0, 0, 255]);
    }
}
