"""What long commands show people: reports as self-contained HTML pages (`html`), progress as they run (`progress`)."""
